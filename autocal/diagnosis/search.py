"""Find the physical effect missing from the forward model (DESIGN.md section 5).

Workflow: fit the current model (per-channel ``G``, ``n`` plus the global parameters of
the accepted effects, :mod:`autocal.diagnosis.effects`), measure the gap (chi^2/dof, rms normalised
residual, low-order Legendre time modes, delay spectra of the residuals and of ``G`` and
``Trxr``, correlation with templates), fit every candidate effect on top, rank them by

    Delta BIC = Delta chi^2 - k ln N

(``chi^2`` radiometer-weighted, ``k`` the candidate's free parameters, ``N`` the number of
data used), and accept the best only if ``Delta BIC > threshold`` (default 10, "very
strong") *and* its ``Delta chi^2`` is significant (chi^2_k survival < ``alpha``). Repeat
until nothing is accepted. ``cable_reflection`` is absorbed by the per-channel gain, so it
is ranked in the bandpass domain: ``chi^2`` of the fitted ``G(nu)`` (with its errors)
against a smooth Legendre bandpass, with and without the ripple, ``N = Nfreq``.

The data's model is never exactly autocal's (another simulator, a real sky), so the
statistic is a quasi-likelihood one (``Delta chi^2`` over the step's overdispersion), and
a candidate is named only when its own signature explains the residual: the two halves of
the band agree on its parameters (:func:`band_consistency`, with a significant partner
fitted alongside when two chromatic effects are missing at once), its own parameters are
significant (:func:`wald_statistic`), a per-integration gain series is not a smooth
function of time (:func:`jitter_is_significant`), and its values are plausible
(:data:`PLAUSIBLE_LIMITS`). Fits start from the current model's values, and a model stuck
in a local minimum is refitted from a candidate's better one
(:func:`_escape_local_minimum`). An effect that barely moves the products
(:func:`is_negligible`) is kept in the model and reported "detected, negligible"; what no
entry explains is described (:func:`describe_unexplained`), not named.
``antenna_gain_jitter`` (every antenna-pol its own series) is fitted feed by feed against
the common ``gain_jitter``, and ``antenna_gain_drift`` (every antenna-pol its own
Legendre drift) likewise (:func:`fit_feed_gains`).

The fit with global parameters is a variable-projection Gauss-Newton: for fixed global
parameters every channel is a weighted linear fit of ``(G, n)``; the global step uses the
Jacobian projected orthogonally to each channel's ``(G, n)`` design, so the covariance of
the global parameters is marginalised over all ``(G, n)``. An optional receiver prior
(``Trxr(nu) = Trxr0 +- sigma``) enters as one pseudo-observation per channel,
``n - Trxr0 G = 0 +- G sigma``.

Scale: the fit streams antennas through its sums a chunk at a time (:func:`antenna_chunks`),
and a fit's model and residuals are computed from its inputs when needed, never stored, so a
whole HERA file (350 antennas, 206 M samples) is diagnosed in ~6 GB. Above
:data:`LARGE_SAMPLES` the weights are float32, fits start from the current model's
parameters and each step scores all candidates in one pass (:func:`screen_candidates`)
before fitting only those that could win in full (:class:`_StepScreen`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import numpy as np
from numpy.polynomial import legendre
from scipy import stats
from threadpoolctl import threadpool_limits

from autocal.compare.delay import delay_spectrum
from autocal.core.observation import Observation
from autocal.diagnosis.effects import (
    DIURNAL_MIN_SPAN_H,
    LST_STEP_H,
    SIDEREAL_RATE,
    Effect,
    SkyTemplates,
    catalogue,
    diurnal_basis,
    time_basis,
)
from autocal.errors import AutocalError
from autocal.fit.model import unwrap_lsts

logger = logging.getLogger(__name__)

P = ParamSpec("P")
R = TypeVar("R")

#: Default Delta BIC an effect must exceed to be accepted.
BIC_THRESHOLD = 10.0
#: Default significance (chi^2_k survival of Delta chi^2) an effect must reach.
ALPHA = 1e-4
#: Most outlier-flagging rounds, each followed by a new search (see :func:`diagnose`).
_OUTLIER_ROUNDS = 3
#: Fraction of a template's Fisher information that must survive the (G, n) projection.
MIN_IDENTIFIABLE = 1e-6
#: Fisher fractions below this are rounding error (``h`` is a difference of sums of squares,
#: :func:`projected_normal_equations`): reported as 0, degenerate with ``(G, n)``.
IDENTIFIABLE_RESOLUTION = 1e-12
#: Smallest singular value (relative) of the scaled normal matrix that is inverted ...
PINV_RTOL = 1e-15
#: ... or this many times its rounding error, if larger (:func:`projected_normal_equations`).
ROUNDING_MARGIN = 100.0


class DiagnoseError(AutocalError):
    """Invalid diagnosis input."""


def _blas_single_thread(func: Callable[P, R]) -> Callable[P, R]:
    """Run ``func`` with BLAS/LAPACK on one thread.

    The extended fit does many small dense solves (a pseudo-inverse of a K x K matrix per
    Gauss-Newton step); multi-threaded OpenBLAS spends ~100x longer on them than one
    thread as soon as the cores are shared (pytest-xdist, other workers): 0.77 s vs 4 ms
    for K = 143 measured on the 2-core development machine under load.
    """

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


# the extended fit -----------------------------------------------------------------------

#: Samples (antenna x pol x integration x channel) in one chunk of antennas of the extended
#: fit and of every pass over its model or residuals. Each channel's ``(G, n)`` belongs to
#: one antenna and the global normal equations and chi^2 are sums over antennas, so the fit
#: streams antennas through its sums; working arrays are a chunk's size, not the
#: observation's, and elementwise work on a chunk of a few MB stays in the processor's
#: caches (one HERA antenna, 0.6 M samples: ~6x faster per sample than 16 antennas at once,
#: ``benchmarks/diagnose_scale.py``).
CHUNK_SAMPLES = 1 << 20
#: Observations with more samples than this are "large": their weights are kept in float32
#: (:func:`radiometer_weights`) and the search screens its candidates by their score before
#: fitting them (:func:`screen_candidates`). Smaller ones are diagnosed exactly as before.
LARGE_SAMPLES = 1 << 24
#: Samples of one ordinary calibration in :func:`product_sigmas` (~0.5 GB of working arrays).
PRODUCT_SIGMA_SAMPLES = 1 << 23


def antenna_chunks(shape: tuple[int, ...], chunk_antennas: int | None = None) -> list[slice]:
    """Return the slices of antennas processed together (:data:`CHUNK_SAMPLES`).

    Parameters
    ----------
    shape
        ``(Nant, Npol, Ntime, Nfreq)``.
    chunk_antennas
        Antennas per chunk (default: as many as :data:`CHUNK_SAMPLES` allows, at least one).
    """
    per_antenna = max(1, math.prod(shape[1:]))
    n = max(1, CHUNK_SAMPLES // per_antenna) if chunk_antennas is None else int(chunk_antennas)
    if n < 1:
        raise DiagnoseError(f"chunks need at least one antenna, got {chunk_antennas}")
    return [slice(i, min(i + n, shape[0])) for i in range(0, shape[0], n)]


def is_large(shape: tuple[int, ...]) -> bool:
    """Return whether an observation of this shape is large (:data:`LARGE_SAMPLES`)."""
    return math.prod(shape) > LARGE_SAMPLES


def _usable_weights(weights: np.ndarray, chan_ok: np.ndarray | None = None) -> np.ndarray:
    """Return a chunk's weights ``(a, P, T, F)`` as float64, zero where unusable.

    Unusable: not finite, not positive, or in a channel without a ``(G, n)`` solution
    (``chan_ok`` ``(a, P, F)`` false).
    """
    w = np.asarray(weights, np.float64)
    ok = np.isfinite(w) & (w > 0)
    if chan_ok is not None:
        ok &= chan_ok[:, :, None, :]
    return np.where(ok, w, 0.0)


@dataclass(frozen=True, eq=False)
class _ModelSource:
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
        return _usable_weights(self.weights[sl], self.chan_ok[sl])

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
        (0 below :data:`IDENTIFIABLE_RESOLUTION`: degenerate with ``(G, n)``).
    iterations
        Gauss-Newton iterations used.
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
    gain_factor: np.ndarray | None = None
    noise_factor: np.ndarray | None = None
    source: _ModelSource | None = field(default=None, repr=False)

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

    def _source(self) -> _ModelSource:
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

    def detached(self) -> ExtendedFit:
        """Return the fit without its :attr:`source` (no reference to data or weights)."""
        return dataclasses.replace(self, source=None)


def weights_dtype(shape: tuple[int, ...]) -> type:
    """Float64 weights, float32 for a large observation (:data:`LARGE_SAMPLES`).

    The weights are held fixed while fits are compared, so their rounding to float32 (a
    relative 6e-8) changes every compared chi^2 alike; every sum is accumulated in float64.
    """
    return np.float32 if is_large(shape) else np.float64


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
        Of the result (default :func:`weights_dtype`).
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


def _split(effects: tuple[Effect, ...]) -> list[tuple[Effect, slice]]:
    out, i = [], 0
    for eff in effects:
        k = 0 if eff.fixed is not None else len(eff.params)
        out.append((eff, slice(i, i + k)))
        i += k
    return out


@dataclass
class _State:
    """One evaluation of the fit: model columns, channel solutions and chi^2.

    ``tt`` ``(P, T, F)`` Tsky; ``gfac``, ``nfac`` ``(T,)`` the gain and noise factors;
    the model is ``G a1 + n a2`` with ``a1 = tt gfac`` and ``a2 = nfac gfac``.
    """

    tt: np.ndarray
    gfac: np.ndarray
    nfac: np.ndarray
    g: np.ndarray
    nn: np.ndarray
    inv: np.ndarray
    good: np.ndarray
    rp: np.ndarray
    chi2: float

    @property
    def a1(self) -> np.ndarray:
        """``(P, T, F)`` the gain's column: Tsky times the gain factor."""
        return self.tt * self.gfac[:, None]

    @property
    def a2(self) -> np.ndarray:
        """``(T,)`` the noise's column: the noise factor times the gain factor."""
        return self.nfac * self.gfac


def _contract(w: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``sum_t w[a, p, t, f] z[p, t, f]`` -> ``(a, P, F)`` (``z`` broadcast to ``(P, T, F)``)."""
    return np.einsum("aptf,ptf->apf", w, np.broadcast_to(z, w.shape[1:]))


class _Problem:
    """The extended fit of one observation, weights and set of effects (:func:`fit_extended`).

    Holds what every evaluation shares (usable channels, prior, bases) and streams the
    antennas through :meth:`evaluate` (channel solutions and chi^2) and
    :meth:`normal_equations` (the projected normal equations of the global parameters,
    the sums of :func:`projected_normal_equations` contracted template by template, so
    that a chunk's samples are read a few times and never copied per parameter).
    """

    def __init__(
        self,
        obs: Observation,
        tpl: SkyTemplates,
        effects: tuple[Effect, ...],
        weights: np.ndarray,
        trxr_prior: np.ndarray | float | None,
        trxr_prior_sigma: np.ndarray | float,
        gain_ref: np.ndarray | None,
        chunk_antennas: int | None,
    ) -> None:
        if tpl.total.shape[0] != len(obs.pols) or tpl.total.shape[1:] != (
            obs.ntime,
            obs.nfreq,
        ):
            raise DiagnoseError("templates do not match the observation's grid")
        weights = np.asarray(weights)
        if weights.shape != obs.shape:
            raise DiagnoseError(f"weights have shape {weights.shape}, the data {obs.shape}")
        self.obs, self.tpl, self.effects, self.weights = obs, tpl, effects, weights
        self.chunks = antenna_chunks(obs.shape, chunk_antennas)
        self.shape3 = shape3 = (obs.nant, len(obs.pols), obs.nfreq)
        # channels with fewer than 3 usable samples cannot constrain (G, n): leave them out
        self.chan_ok = np.zeros(shape3, bool)
        self.used = 0
        # weights finite and >= 0, data finite: the chunks are used as they are
        self.clean_weights = self.finite_data = True
        for sl in self.chunks:
            w = weights[sl]
            usable = np.isfinite(w) & (w > 0)
            self.clean_weights &= bool(np.all(usable | (w == 0)))
            self.finite_data &= bool(np.all(np.isfinite(obs.data[sl])))
            nuse = usable.sum(axis=2)
            self.chan_ok[sl] = nuse >= 3
            self.used += int(nuse[self.chan_ok[sl]].sum())
        if not self.chan_ok.any():
            raise DiagnoseError("no channel has 3 or more unflagged samples to fit")
        self.blocks = _split(effects)
        self.nfree = sum(b.stop - b.start for _, b in self.blocks)
        self.fixed = {e.name: np.asarray(e.fixed, float) for e in effects if e.fixed is not None}
        self.bases = {
            (e.basis, e.order): e.time_basis(obs.lsts) for e in effects if e.kind != "tsky"
        }
        self.prior = trxr_prior is not None
        t0 = np.broadcast_to(np.asarray(trxr_prior if self.prior else 0.0, float), shape3)
        sig0 = np.broadcast_to(np.asarray(trxr_prior_sigma, float), shape3)
        has_prior = np.isfinite(t0) & np.isfinite(sig0) & (sig0 > 0)
        self.t0 = np.where(has_prior, t0, 0.0)
        # prior weights from a reference gain
        self.wp = np.zeros(shape3)
        if self.prior:
            with np.errstate(over="ignore", invalid="ignore", under="ignore"):
                if gain_ref is None:
                    gain_ref = self.evaluate(np.zeros(self.nfree)).g
                gain_ref = np.where(np.abs(gain_ref) > 0, np.abs(gain_ref), np.inf)
                self.wp = np.where(self.chan_ok & has_prior, 1.0 / (gain_ref * sig0) ** 2, 0.0)

    def values(self, eff: Effect, sl: slice, pv: np.ndarray) -> np.ndarray:
        """Return an effect's parameter values (its fixed values, or ``pv[sl]``)."""
        return self.fixed[eff.name] if eff.fixed is not None else pv[sl]

    def chunk_arrays(self, sl: slice) -> tuple[np.ndarray, np.ndarray]:
        """Return weights and data of antennas ``sl``, ``(a, P, T, F)`` float64.

        Weights are zero where unusable (channels without a solution included), data
        zero where not finite; both are views of the inputs when nothing needs zeroing.
        """
        ok = self.chan_ok[sl]
        if self.clean_weights:
            w = np.asarray(self.weights[sl], np.float64)
            if not ok.all():
                w = w * ok[:, :, None, :]
        else:
            w = _usable_weights(self.weights[sl], ok)
        y = self.obs.data[sl]
        if not self.finite_data:
            with np.errstate(invalid="ignore"):
                y = np.where(w > 0, y, 0.0)
        return w, y

    def columns(self, pv: np.ndarray) -> tuple[np.ndarray, ...]:
        """Return Tsky ``(P, T, F)`` and the gain and noise factors ``(T,)`` at ``pv``."""
        tsky = self.tpl.total.copy()
        gfac = np.ones(self.obs.ntime)
        nfac = np.ones(self.obs.ntime)
        for eff, sl in self.blocks:
            v = self.values(eff, sl, pv)
            if eff.kind == "tsky":
                tsky = tsky + eff.delta(v, self.tpl)
            elif eff.kind == "gain":
                gfac = gfac + v @ self.bases[eff.basis, eff.order]
            else:
                nfac = nfac + v @ self.bases[eff.basis, eff.order]
        return tsky, gfac, nfac

    @staticmethod
    def residual(
        y: np.ndarray, g: np.ndarray, nn: np.ndarray, a1: np.ndarray, a2: np.ndarray
    ) -> np.ndarray:
        """Return ``y - G a1 - n a2`` of a chunk (``a1`` ``(P, T, F)``, ``a2`` ``(T,)``)."""
        r = g[:, :, None, :] * a1
        r += nn[:, :, None, :] * a2[:, None]
        np.subtract(y, r, out=r)
        return r

    def evaluate(self, pv: np.ndarray) -> _State:
        """Solve every channel's ``(G, n)`` at global parameters ``pv``; chi^2."""
        tt, gfac, nfac = self.columns(pv)
        a1 = tt * gfac[:, None]
        a2 = nfac * gfac
        a1sq, a12, a2sq = a1 * a1, a1 * a2[:, None], (a2 * a2)[:, None]
        shape3 = self.shape3
        g, nn = np.zeros(shape3), np.zeros(shape3)
        inv, good = np.zeros((3, *shape3)), np.zeros(shape3, bool)
        chi2 = 0.0
        for sl in self.chunks:
            w, y = self.chunk_arrays(sl)
            wp, t0 = self.wp[sl], self.t0[sl]
            wy = w * y
            n11 = _contract(w, a1sq) + wp * t0**2
            n12 = _contract(w, a12) - wp * t0
            n22 = _contract(w, a2sq) + wp
            b1 = _contract(wy, a1)
            b2 = _contract(wy, a2[:, None])
            det = n11 * n22 - n12**2
            ok = self.chan_ok[sl] & np.isfinite(det) & (det > 1e-12 * np.abs(n11 * n22))
            det = np.where(ok, det, 1.0)
            iv = np.where(ok, np.stack([n22 / det, -n12 / det, n11 / det]), 0.0)
            gc = iv[0] * b1 + iv[1] * b2
            nc = iv[1] * b1 + iv[2] * b2
            g[sl], nn[sl], inv[:, sl], good[sl] = gc, nc, iv, ok
            r = self.residual(y, gc, nc, a1, a2)
            chi2 += float(np.einsum("aptf,aptf,aptf->", w, r, r))
        rp = np.where(good, -(nn - self.t0 * g), 0.0)
        chi2 += float((self.wp * rp**2).sum())
        return _State(tt, gfac, nfac, g, nn, inv, good, rp, chi2)

    def _terms(self, pv: np.ndarray, st: _State) -> list[tuple[slice, list, np.ndarray, str]]:
        """Return each free block's factorised derivative ``sum_m alpha_m beta_m Y``.

        ``(slice, [(alpha, beta)], Y, form)``: ``alpha`` ``"g"`` or ``"n"`` (the channel's
        fitted gain or noise), ``beta`` broadcastable to ``(P, T, F)``, ``Y`` ``(P, T, F,
        k)`` (``form`` ``"tsky"``), a time basis ``(T, k)`` (``"time"``) or the
        per-integration basis (``"integration"``, parameter ``k`` = integration ``k + 1``).
        """
        out = []
        gcol, ncol = st.gfac[:, None], st.nfac[:, None]
        for eff, sl in self.blocks:
            if sl.stop == sl.start:
                continue
            if eff.kind == "tsky":
                terms = [("g", gcol)]
                ymat, form = eff.jacobian(pv[sl], self.tpl), "tsky"
            else:
                terms = [("g", st.tt), ("n", ncol)] if eff.kind == "gain" else [("n", gcol)]
                ymat = self.bases[eff.basis, eff.order].T
                form = "integration" if eff.basis == "integration" else "time"
            out.append((sl, terms, ymat, form))
        return out

    def normal_equations(
        self, pv: np.ndarray, st: _State, groups: list[int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``h``, ``grad``, ``raw`` (:func:`projected_normal_equations`) at ``st``.

        ``groups``: one per free block; the ``J^T W J`` block of two blocks of different
        nonzero groups is not computed (left 0; see :func:`screen_candidates`).
        """
        specs = self._terms(pv, st)
        nfree = self.nfree
        a1, a2 = st.a1, st.a2
        a2col = a2[:, None]
        products = {
            tuple(sorted(a + b))
            for _, t1, _, _ in specs
            for _, t2, _, _ in specs
            for a, _ in t1
            for b, _ in t2
        }
        wsum = {key: np.zeros(a1.shape) for key in products}  # sum_a w alpha alpha'
        proj = np.zeros((nfree, nfree))
        grad = np.zeros(nfree)
        for sl in self.chunks:
            w, y = self.chunk_arrays(sl)
            alpha = {"g": st.g[sl], "n": st.nn[sl]}
            wr = w * self.residual(y, alpha["g"], alpha["n"], a1, a2)
            rp, wp, t0 = st.rp[sl], self.wp[sl], self.t0[sl]
            # A^T W r per channel (data and prior rows): ~0 at the channel solution
            q1 = _contract(wr, a1) - wp * t0 * rp
            q2 = _contract(wr, a2col) + wp * rp
            for key in wsum:
                wsum[key] += np.einsum("aptf,apf->ptf", w, alpha[key[0]] * alpha[key[1]])
            c1 = np.zeros((*alpha["g"].shape, nfree))
            c2 = np.zeros_like(c1)
            for bsl, terms, ymat, form in specs:
                for name, beta in terms:
                    al = alpha[name]
                    if form == "integration":
                        # one parameter per integration: the sums over time are the samples
                        for col, dst in ((a1 * beta, c1), (a2col * beta, c2)):
                            dst[..., bsl] += al[..., None] * np.moveaxis(
                                (w * col)[:, :, 1:, :], 2, -1
                            )
                        grad[bsl] += np.einsum("apf,aptf->t", al, wr * beta)[1:]
                        continue
                    for k in range(ymat.shape[-1]):
                        z = beta * (ymat[..., k] if form == "tsky" else ymat[:, k, None])
                        i = bsl.start + k
                        c1[..., i] += al * _contract(w, a1 * z)
                        c2[..., i] += al * _contract(w, a2col * z)
                        grad[i] += float(np.sum(al * _contract(wr, z)))
            inv = st.inv[:, sl]
            k1 = inv[0][..., None] * c1 + inv[1][..., None] * c2
            k2 = inv[1][..., None] * c1 + inv[2][..., None] * c2
            c1, c2, k1, k2 = (x.reshape(-1, nfree) for x in (c1, c2, k1, k2))
            proj += c1.T @ k1 + c2.T @ k2
            grad -= k1.T @ q1.reshape(-1) + k2.T @ q2.reshape(-1)
        # J^T W J from the antenna sums: sum_{p,t,f} (sum_a w alpha alpha') beta beta' Y Y'
        jwj = np.zeros((nfree, nfree))
        grp = [0] * len(specs) if groups is None else groups
        for i, (sl1, t1, y1, f1) in enumerate(specs):
            for j in range(i, len(specs)):
                sl2, t2, y2, f2 = specs[j]
                if grp[i] and grp[j] and grp[i] != grp[j]:
                    continue
                v = sum(wsum[tuple(sorted(n1 + n2))] * b1 * b2 for n1, b1 in t1 for n2, b2 in t2)
                block = _pair_sum(np.broadcast_to(v, a1.shape), y1, f1, y2, f2)
                jwj[sl1, sl2] = block
                jwj[sl2, sl1] = block.T
        h = jwj - proj
        return 0.5 * (h + h.T), grad, np.diag(jwj).copy()


def _pair_sum(v: np.ndarray, y1: np.ndarray, f1: str, y2: np.ndarray, f2: str) -> np.ndarray:
    """``sum_{p,t,f} v Y1[..., k] Y2[..., l]`` for Tsky ``(P, T, F, k)`` or time ``(T, k)`` Y."""
    if f1 != "tsky" and f2 != "tsky":
        return (y1.T * v.sum(axis=(0, 2))) @ y2
    if f1 == "tsky" and f2 == "tsky":
        return np.einsum("ptf,ptfk,ptfl->kl", v, y1, y2)
    if f1 == "tsky":
        return np.einsum("ptf,ptfk->tk", v, y1).T @ y2
    return y1.T @ np.einsum("ptf,ptfl->tl", v, y2)


@_blas_single_thread
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

    Antennas are streamed through the fit in chunks (:func:`antenna_chunks`): each
    channel's ``(G, n)`` is solved within its chunk and the global normal equations and
    chi^2 are summed over chunks, so memory holds the observation, the weights and a
    chunk's working arrays; the result does not depend on the chunking (up to rounding).

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
        ``(Nant, Npol, Nfreq)`` gain used to scale the prior's sigma (default: a fit
        without prior).
    max_iter, tol
        Gauss-Newton limits (``tol`` in units of the parameter sigma).
    start
        ``{effect name: values}`` to start Gauss-Newton from (default zero: no effect);
        entries whose length does not match the effect's free parameters are ignored.
    chunk_antennas
        Antennas per chunk (default :data:`CHUNK_SAMPLES`).

    Returns
    -------
    ExtendedFit
        The fit.
    """
    effects = tuple(e for e in effects if e.kind not in ("bandpass", "feed_gain"))
    prob = _Problem(
        obs, tpl, effects, weights, trxr_prior, trxr_prior_sigma, gain_ref, chunk_antennas
    )
    blocks, nfree = prob.blocks, prob.nfree
    p = np.zeros(nfree)
    for eff, sl in blocks:
        init = None if start is None else start.get(eff.name)
        if init is not None and sl.stop > sl.start and np.size(init) == sl.stop - sl.start:
            p[sl] = np.where(np.isfinite(init), init, 0.0)
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        st = prob.evaluate(p)
        if not np.isfinite(st.chi2):
            raise DiagnoseError(
                "the baseline fit is not finite: check the data for unflagged zeros, "
                "infinities or absurd values"
            )
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
                ident = _identifiable(blocks, h, raw)
                if any(ident.get(e.name, 1.0) < MIN_IDENTIFIABLE for e, _ in blocks):
                    cov = np.full((nfree, nfree), np.inf)
                    break
            cov = _scaled_pinv(h, raw)
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
    chi2 = st.chi2
    g, nn = np.where(st.good, st.g, np.nan), np.where(st.good, st.nn, np.nan)
    nchan = int(st.good.sum())
    ndata = prob.used + (nchan if prob.prior else 0)
    params: dict[str, np.ndarray] = {}
    sigmas: dict[str, np.ndarray] = {}
    sig_all = np.sqrt(np.abs(np.diag(cov))) if nfree else np.zeros(0)
    for eff, sl in blocks:
        params[eff.name] = prob.values(eff, sl, p).copy()
        sigmas[eff.name] = (
            np.zeros(len(eff.params)) if eff.fixed is not None else sig_all[sl].copy()
        )
    source = _ModelSource(
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
        effects=effects,
        params=params,
        sigmas=sigmas,
        G=g,
        n=nn,
        sigma_G=np.where(st.good, np.sqrt(np.abs(st.inv[0])), np.nan),
        chi2=chi2,
        ndata=ndata,
        nparam=2 * nchan + nfree,
        identifiable=ident,
        iterations=it,
        gain_factor=np.asarray(st.gfac, float).copy(),
        noise_factor=np.asarray(st.nfac, float).copy(),
        source=source,
    )


def _identifiable(
    blocks: list[tuple[Effect, slice]], h: np.ndarray, raw: np.ndarray
) -> dict[str, float]:
    """Return each free block's Fisher fraction left after the ``(G, n)`` projection."""
    ident: dict[str, float] = {}
    for eff, sl in blocks:
        if sl.stop > sl.start:
            frac = float(np.min(np.diag(h)[sl] / np.where(raw[sl] > 0, raw[sl], np.inf)))
            ident[eff.name] = frac if frac >= IDENTIFIABLE_RESOLUTION else 0.0
    return ident


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
        Fraction of the candidate's Fisher information left after the ``(G, n)``
        projection (as :attr:`ExtendedFit.identifiable`, at the current model).
    """

    delta_chi2: float
    identifiable: float


@_blas_single_thread
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
        As for :func:`fit_extended` (the weights of ``current``).
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
    prob = _Problem(obs, tpl, effects, weights, trxr_prior, trxr_prior_sigma, gain_ref, None)
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
        frac = _identifiable([(eff, sl)], h, raw).get(eff.name, 0.0)
        if (
            sl.stop == sl.start
            or frac < MIN_IDENTIFIABLE
            or not np.all(np.isfinite(h[idx][:, idx]))
        ):
            out.append(Screening(0.0, frac))
            continue
        hs = h[np.ix_(idx, idx)]
        gs = grad[idx]
        dchi = float(gs @ _scaled_pinv(hs, raw[idx]) @ gs)
        out.append(Screening(max(dchi, 0.0), frac))
    return out


def _scaled_pinv(h: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of the projected normal matrix ``h`` (``raw``: its unprojected diagonal).

    ``h`` is scaled to unit diagonal first (parameters differ by 1e6); it is ``J^T W J``
    less the ``(G, n)`` part, so its rounding error is ~eps * raw / diag(h) of the scaled
    matrix: directions below that are left out, not inverted.
    """
    hdiag = np.diag(h)
    dscale = 1.0 / np.sqrt(np.where(hdiag > 0, hdiag, 1.0))
    lost = np.max(np.where(hdiag > 0, raw * dscale**2, 1.0))  # raw / projected
    rtol = max(PINV_RTOL, ROUNDING_MARGIN * np.finfo(float).eps * lost)
    return dscale[:, None] * np.linalg.pinv(dscale[:, None] * h * dscale, rtol=rtol) * dscale


# normal equations of the global parameters ------------------------------------------------
#
# The model's derivative with respect to each effect's parameters factorises into a part
# that depends on the antenna and a part that does not: J[a, p, f, t, k] = X[a, p, f, t] *
# Y[p, f, t, k], with Y = the time basis (gain and noise drifts; no p, f dependence) or the
# Tsky template's derivative (shared by all antennas). The Gauss-Newton normal matrix with
# the per-channel (G, n) projected out (variable projection) is
#     h = J^T W J - sum over channels of (c1 k1^T + c2 k2^T),
#     c_i = sum_t w a_i J,  (k1, k2) = N^-1 (c1, c2),  N the channel's 2 x 2 normal matrix,
# so only J^T W J (antennas summed first, then the small bases), the c_i (one matrix product
# per effect over time) and K x K products are needed: never the (samples x K) Jacobian,
# which took most of a diagnosis's time and ~8 bytes x samples x K of memory. Every term is
# a sum over antennas, so the fit adds them up a chunk of antennas at a time.


def _sum_time(v: np.ndarray, ymat: np.ndarray) -> np.ndarray:
    """``sum_t v[a, p, f, t] Y[p, f, t, k]`` -> ``(A, P, F, k)``."""
    if ymat.shape[:2] == (1, 1):
        return (v.reshape(-1, v.shape[-1]) @ ymat[0, 0]).reshape(*v.shape[:3], -1)
    return np.matmul(v[..., None, :], ymat)[..., 0, :]


def _sum_all(z: np.ndarray, ymat: np.ndarray) -> np.ndarray:
    """``sum_{p, f, t} z[p, f, t] Y[p, f, t, k]`` -> ``(k,)``."""
    if ymat.shape[:2] == (1, 1):
        return z.sum(axis=(0, 1)) @ ymat[0, 0]
    return np.einsum("pft,pftk->k", z, ymat)


def _sum_pair(z: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """``sum_{p, f, t} z Y1[..., k] Y2[..., l]`` -> ``(k, l)``."""
    if y1.shape[:2] == (1, 1) and y2.shape[:2] == (1, 1):
        return (y1[0, 0].T * z.sum(axis=(0, 1))) @ y2[0, 0]
    b1 = np.broadcast_to(y1, (*z.shape, y1.shape[-1])).reshape(-1, y1.shape[-1])
    b2 = np.broadcast_to(y2, (*z.shape, y2.shape[-1])).reshape(-1, y2.shape[-1])
    return (z.reshape(-1, 1) * b1).T @ b2


def projected_normal_equations(
    factors: list[tuple[slice, np.ndarray, np.ndarray]],
    w: np.ndarray,
    wa1: np.ndarray,
    wa2: np.ndarray,
    inv: np.ndarray,
    r: np.ndarray,
    q1: np.ndarray,
    q2: np.ndarray,
    nfree: int,
    groups: list[int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton normal equations of the global parameters, ``(G, n)`` projected out.

    Parameters
    ----------
    factors
        ``(slice, X, Y)`` of the free parameters: ``X`` broadcastable to ``w``, ``Y``
        ``(P, F, T, k)`` or, for a time basis, ``(1, 1, T, k)``.
    w, wa1, wa2
        ``(A, P, F, T)`` weights and the weighted ``(G, n)`` columns ``w a1``, ``w a2``.
    inv
        ``(3, A, P, F)`` inverse of each channel's 2 x 2 normal matrix (``[0, 0]``,
        ``[0, 1]``, ``[1, 1]``; zero for channels without a solution).
    r
        ``(A, P, F, T)`` residuals.
    q1, q2
        ``(A, P, F)`` ``A^T W r`` of each channel (data and prior rows).
    nfree
        Number of free global parameters.
    groups
        One per factor: the ``J^T W J`` block of two factors whose groups differ and are
        both nonzero is left 0 (its projection part is still subtracted); default all 0.

    Returns
    -------
    h, grad, raw
        ``(K, K)`` normal matrix and ``(K,)`` gradient of the projected problem (those the
        projected Jacobian ``J - a1 k1 - a2 k2`` gives, with the prior rows), and the
        diagonal of ``J^T W J`` before the projection (identifiability).
    """
    jwj = np.zeros((nfree, nfree))
    grad = np.zeros(nfree)
    c1 = np.zeros((*w.shape[:3], nfree))
    c2 = np.zeros_like(c1)
    grp = [0] * len(factors) if groups is None else groups
    for i, (sl, x, ymat) in enumerate(factors):
        wx = w * x
        c1[..., sl] = _sum_time(wa1 * x, ymat)
        c2[..., sl] = _sum_time(wa2 * x, ymat)
        grad[sl] = _sum_all((wx * r).sum(axis=0), ymat)
        for j, (sl2, x2, y2) in enumerate(factors[i:], i):
            if grp[i] and grp[j] and grp[i] != grp[j]:
                continue
            block = _sum_pair(np.broadcast_to(wx * x2, w.shape).sum(axis=0), ymat, y2)
            jwj[sl, sl2] = block
            jwj[sl2, sl] = block.T
    k1 = inv[0][..., None] * c1 + inv[1][..., None] * c2
    k2 = inv[1][..., None] * c1 + inv[2][..., None] * c2
    c1, c2, k1, k2 = (a.reshape(-1, nfree) for a in (c1, c2, k1, k2))
    h = jwj - c1.T @ k1 - c2.T @ k2
    grad -= k1.T @ q1.reshape(-1) + k2.T @ q2.reshape(-1)
    return 0.5 * (h + h.T), grad, np.diag(jwj).copy()


#: Compare-exchange pairs of a median-of-9 sorting network (19 exchanges; Paeth, Devillard):
#: afterwards element 4 holds the median.
_MEDIAN9 = (
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 1),
    (3, 4),
    (6, 7),
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 3),
    (5, 8),
    (4, 7),
    (3, 6),
    (1, 4),
    (2, 5),
    (4, 7),
    (4, 2),
    (6, 4),
    (4, 2),
)


def _running_median(x: np.ndarray, window: int, axis: int) -> np.ndarray:
    """Return the running median of ``x`` over ``window`` samples along ``axis``.

    That of ``scipy.ndimage.median_filter`` (mode ``"mirror"``, a footprint along ``axis``
    only). A window of 9 over an axis longer than 9 uses a sorting network on whole arrays (the
    same values as ``median_filter``, ~4x faster on a HERA antenna); other windows call
    ``median_filter``.
    """
    n = x.shape[axis]
    if window != 9 or n <= window:
        from scipy.ndimage import median_filter

        size = [1] * x.ndim
        size[axis] = window
        return median_filter(x, size=tuple(size), mode="mirror")
    half = window // 2
    pad = [(0, 0)] * x.ndim
    pad[axis] = (half, half)
    xp = np.pad(x, pad, mode="reflect")  # scipy's "mirror"
    lead = (slice(None),) * (axis % x.ndim)
    p = [np.array(xp[(*lead, slice(i, i + n))]) for i in range(window)]
    for a, b in _MEDIAN9:
        low = np.minimum(p[a], p[b])
        np.maximum(p[a], p[b], out=p[b])
        p[a] = low
    return p[4]


def _residual_pieces(fit: Any) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(antenna slice, residuals)`` of a fit chunk by chunk.

    Anything else with a ``residuals`` array gives it whole.
    """
    if hasattr(fit, "residual_chunks"):
        yield from fit.residual_chunks()
    else:
        res = np.asarray(fit.residuals)
        yield slice(0, res.shape[0]), res


def flag_outliers(
    obs: Observation,
    fit: ExtendedFit,
    *,
    threshold: float = 6.0,
    window: int = 9,
    max_fraction: float = 0.5,
) -> np.ndarray:
    """Flag narrow-band or impulsive outliers (RFI) in the residuals of a fit.

    The normalised residuals are high-passed by subtracting their running median over
    ``window`` integrations and then over ``window`` channels, so structure smooth in
    time or in frequency (the signatures of every catalogue effect, and the bending of
    a channel's fit by an outlier) is left alone and only features a few samples wide
    are flagged: samples deviating by more than ``threshold`` robust sigma
    (1.4826 x the median absolute deviation over all samples). A channel (integration)
    that loses more than ``max_fraction`` of its samples is flagged entirely. The
    residuals are filtered a chunk of antennas at a time; the high-passed values of a
    large observation (:func:`is_large`) are kept in float32 for the median over all.

    Parameters
    ----------
    obs
        The observation the fit was made to.
    fit
        A fit of it (:func:`fit_extended`).
    threshold
        Robust sigmas beyond which a sample is an outlier.
    window
        Integrations and channels of the running medians.
    max_fraction
        Fraction of flagged samples above which a whole channel or integration is flagged.

    Returns
    -------
    numpy.ndarray
        ``(Nant, Npol, Ntime, Nfreq)`` flags (the observation's own included).
    """
    dev = np.empty(obs.shape, weights_dtype(obs.shape))
    usable = np.zeros(obs.shape, bool)
    for sl, res in _residual_pieces(fit):
        ok = np.isfinite(res)
        usable[sl] = ok
        # high-pass in time, then in frequency: what a fit bent by an outlier spreads over
        # its channel is smooth in time and goes; the outlier itself stays
        filled = np.where(ok, res, 0.0)
        hp = filled - _running_median(filled, window, axis=2)
        hp = hp - _running_median(hp, window, axis=3)
        dev[sl] = np.where(ok, hp, np.nan)
    if not usable.any():
        return obs.flags.copy()
    centre = np.nanmedian(dev)
    np.subtract(dev, centre, out=dev)
    np.abs(dev, out=dev)  # in place: |deviation from the centre|
    sigma = 1.4826 * np.nanmedian(dev)
    if not np.isfinite(sigma) or sigma <= 0:
        return obs.flags.copy()
    flags = obs.flags.copy()
    for sl in antenna_chunks(obs.shape):
        ok = usable[sl]
        new = ok & (dev[sl] > threshold * sigma)
        count = np.maximum(ok.sum(axis=2, keepdims=True), 1)
        new |= (new.sum(axis=2, keepdims=True) / count > max_fraction) & ok
        count = np.maximum(ok.sum(axis=3, keepdims=True), 1)
        new |= (new.sum(axis=3, keepdims=True) / count > max_fraction) & ok
        flags[sl] |= new
    return flags


# the bandpass domain --------------------------------------------------------------------


@dataclass(frozen=True)
class BandpassFit:
    """Fit of the fitted ``G(nu)`` by a smooth bandpass, optionally times a ripple.

    Attributes
    ----------
    chi2, nfreq, nparam
        Chi-square over channels (all antennas and pols), channels, parameters.
    a, sigma_a, tau_ns, sigma_tau_ns, phi, sigma_phi
        Ripple parameters (``NaN`` for the smooth fit); the delay is shared by all
        antennas and pols, ``a`` and ``phi`` are those of the first (see ``per_feed``).
    per_feed
        ``a``, ``phi`` and their sigmas for every antenna/pol row, in order.
    at_edge
        The best delay lies within one resolution element of the searched range's ends:
        unresolved bandpass structure rather than a reflection.
    smooth_order
        Legendre order of the smooth bandpass.
    masked_channels
        Channels left out as narrow-band outliers of the smooth bandpass.
    """

    chi2: float
    nfreq: int
    nparam: int
    a: float = float("nan")
    sigma_a: float = float("nan")
    tau_ns: float = float("nan")
    sigma_tau_ns: float = float("nan")
    phi: float = float("nan")
    sigma_phi: float = float("nan")
    per_feed: tuple[dict[str, float], ...] = ()
    at_edge: bool = False
    smooth_order: int = 0
    masked_channels: int = 0

    @property
    def reduced_chi2(self) -> float:
        """``chi^2 / dof``."""
        return self.chi2 / max(self.nfreq - self.nparam, 1)


def _bandpass_chi2(
    freqs: np.ndarray, g: np.ndarray, sg: np.ndarray, order: int, tau: float | None
) -> tuple[float, np.ndarray, np.ndarray]:
    x = 2 * (freqs - freqs[0]) / (freqs[-1] - freqs[0]) - 1
    basis = legendre.legvander(x, order)  # (F, O+1)
    ok = np.isfinite(g) & np.isfinite(sg) & (sg > 0)
    wsq = np.where(ok, 1 / np.where(ok, sg, 1.0), 0.0)
    smooth_coef = np.linalg.lstsq(basis * wsq[:, None], np.where(ok, g, 0) * wsq, rcond=None)[0]
    if tau is None:
        cols = basis
    else:
        smooth = basis @ smooth_coef
        ph = 2 * np.pi * freqs * tau
        cols = np.hstack([basis, (smooth * np.cos(ph))[:, None], (smooth * np.sin(ph))[:, None]])
    a = cols * wsq[:, None]
    coef, *_ = np.linalg.lstsq(a, np.where(ok, g, 0) * wsq, rcond=None)
    chi2 = float(np.sum((a @ coef - np.where(ok, g, 0) * wsq) ** 2))
    cov = np.linalg.pinv(a.T @ a)
    return chi2, coef, cov


class _RippleScan:
    """Total chi^2 of :func:`_bandpass_chi2` with a ripple, summed over rows, for many delays.

    The same least-squares fits, all rows at once: each row's weighted smooth basis is
    factorised once (QR), and for every delay only the two ripple columns are projected
    off it, so a scan costs a few batched matrix products per delay instead of a
    least-squares solve per row and delay (a whole HERA file has 700 rows and ~370
    delays). Rows whose smooth basis is (nearly) rank-deficient over their usable channels
    are fitted one by one as before.
    """

    def __init__(self, freqs: np.ndarray, g2: np.ndarray, s2: np.ndarray, order: int) -> None:
        x = 2 * (freqs - freqs[0]) / (freqs[-1] - freqs[0]) - 1
        basis = legendre.legvander(x, order)  # (F, O+1)
        ok = np.isfinite(g2) & np.isfinite(s2) & (s2 > 0)
        wsq = np.where(ok, 1 / np.where(ok, s2, 1.0), 0.0)  # (R, F)
        b = np.where(ok, g2, 0.0) * wsq
        a = basis[None] * wsq[..., None]  # (R, F, O+1)
        q, r = np.linalg.qr(a)
        diag = np.abs(np.diagonal(r, axis1=1, axis2=2))
        full = (ok.sum(axis=1) > order + 3) & (diag.min(axis=1) > 1e-10 * diag.max(axis=1))
        self.freqs, self.order = freqs, order
        self.rows = [(g2[i], s2[i]) for i in np.flatnonzero(~full)]
        q, r, b, wsq = q[full], r[full], b[full], wsq[full]
        qtb = np.einsum("rfk,rf->rk", q, b)
        self.resid = b - np.einsum("rfk,rk->rf", q, qtb)  # off the smooth basis
        self.null = (self.resid**2).sum(axis=1)
        coef = np.linalg.solve(r, qtb[..., None])[..., 0]  # smooth fit of each row
        smooth_w = (coef @ basis.T) * wsq  # weighted smooth bandpass (R, F)
        # the ripple columns are smooth_w cos / sin: with c = s cos(2 pi nu tau) etc.,
        # Q^T c = (Q s)^T cos and |c - Q Q^T c|^2 = |c|^2 - |Q^T c|^2 (Q orthonormal), and
        # the residual is orthogonal to Q: every delay needs three small matrix products
        self.qs = np.ascontiguousarray(np.swapaxes(q * smooth_w[..., None], 1, 2))  # (R, K, F)
        self.s2 = smooth_w**2
        self.sr = smooth_w * self.resid

    def __call__(self, tau_s: float) -> float:
        """Return the total chi^2 with a ripple of delay ``tau_s`` (seconds)."""
        ph = 2 * np.pi * self.freqs * tau_s
        cs = np.stack([np.cos(ph), np.sin(ph)], axis=-1)  # (F, 2)
        qtc = (self.qs.reshape(-1, cs.shape[0]) @ cs).reshape(*self.qs.shape[:2], 2)
        trig = np.stack([cs[:, 0] ** 2, cs[:, 0] * cs[:, 1], cs[:, 1] ** 2], axis=-1)
        cc = self.s2 @ trig  # (R, 3): c^T c
        m = np.stack([cc[:, 0], cc[:, 1], cc[:, 1], cc[:, 2]], axis=-1).reshape(-1, 2, 2)
        m = m - np.swapaxes(qtc, 1, 2) @ qtc
        v = self.sr @ cs  # (R, 2)
        gain = np.einsum("rk,rkl,rl->r", v, np.linalg.pinv(m, hermitian=True), v)
        total = float(np.sum(self.null - gain))
        for g, s in self.rows:
            total += _bandpass_chi2(self.freqs, g, s, self.order, tau_s)[0]
        return total


def auto_smooth_order(freqs: np.ndarray, min_delay_ns: float = 100.0) -> int:
    """Legendre order of a smooth bandpass that leaves delays >= ``min_delay_ns`` alone.

    A Legendre series of order ``N`` over a band ``B`` absorbs ripples of delay up to
    about ``N / (3.3 B)`` (>= 90 % of the variance of a cosine at ``N / (1.5 B)`` is
    left), so ``N = round(1.5 B min_delay)``, clipped to 4..24.
    """
    bandwidth = float(abs(freqs[-1] - freqs[0]))
    return int(np.clip(round(1.5 * bandwidth * min_delay_ns * 1e-9), 4, 24))


def _narrowband_outliers(
    freqs: np.ndarray, g: np.ndarray, sg: np.ndarray, order: int, threshold: float = 6.0
) -> np.ndarray:
    """Channels whose gain departs from the smooth bandpass by a narrow feature (RFI)."""
    from scipy.ndimage import median_filter

    x = 2 * (freqs - freqs[0]) / (freqs[-1] - freqs[0]) - 1
    ok = np.isfinite(g) & np.isfinite(sg) & (sg > 0)
    if ok.sum() <= order + 2:
        return ~ok
    coef = legendre.legfit(x[ok], g[ok], order, w=1 / sg[ok])
    r = np.where(ok, (g - legendre.legval(x, coef)) / np.where(ok, sg, 1.0), 0.0)
    dev = r - median_filter(r, size=9, mode="mirror")
    sigma = 1.4826 * np.median(np.abs(dev[ok] - np.median(dev[ok])))
    if not np.isfinite(sigma) or sigma <= 0:
        return ~ok
    return ~ok | (np.abs(dev - np.median(dev[ok])) > threshold * sigma)


def fit_cable_reflection(
    freqs: np.ndarray,
    gain: np.ndarray,
    sigma_gain: np.ndarray,
    *,
    smooth_order: int | None = None,
    tau_range_ns: tuple[float, float] = (90.0, 500.0),
) -> tuple[BandpassFit, BandpassFit]:
    """Fit ``G(nu)`` by a smooth Legendre bandpass, and by the same times ``1 + a cos``.

    The ripple is linearised, ``P(nu) + Pbar(nu) (c cos 2 pi nu tau + s sin 2 pi nu tau)``
    with ``Pbar`` the smooth fit; ``tau`` is scanned on a grid oversampled 8x relative to
    the delay resolution ``1 / bandwidth`` and refined parabolically; its error is where
    ``chi^2`` rises by 1. The delay is common to all antennas and polarisations, the
    amplitude and phase are fitted for each (``per_feed``). Channels with narrow-band
    outliers from the smooth bandpass (RFI absorbed by the per-channel gain) are left out
    of both fits.

    Parameters
    ----------
    freqs
        ``(Nfreq,)`` Hz.
    gain, sigma_gain
        ``(..., Nfreq)`` fitted gain and its 1-sigma.
    smooth_order
        Legendre order of the smooth bandpass (default :func:`auto_smooth_order` for the
        shortest searched delay).
    tau_range_ns
        Delays scanned (capped at the Nyquist delay ``1 / (2 dnu)``).

    Returns
    -------
    (BandpassFit, BandpassFit)
        Smooth fit and smooth-with-ripple fit.
    """
    order = auto_smooth_order(freqs, tau_range_ns[0]) if smooth_order is None else smooth_order
    g2 = np.asarray(gain, float).reshape(-1, freqs.size)
    s2 = np.asarray(sigma_gain, float).reshape(-1, freqs.size).copy()
    masked = 0
    for i in range(g2.shape[0]):
        bad = _narrowband_outliers(freqs, g2[i], s2[i], order)
        masked += int((bad & np.isfinite(g2[i])).sum())
        s2[i, bad] = np.nan
    nyq = 0.5 / abs(freqs[1] - freqs[0]) * 1e9
    hi = min(tau_range_ns[1], 0.95 * nyq)
    resolution = 1e9 / (freqs[-1] - freqs[0])
    grid = np.arange(tau_range_ns[0], hi, resolution / 8)
    rows = list(zip(g2, s2, strict=True))
    nused = int((np.isfinite(g2) & np.isfinite(s2)).sum())

    def total_chi2(tau_s: float | None) -> float:
        return sum(_bandpass_chi2(freqs, g, s, order, tau_s)[0] for g, s in rows)

    null = BandpassFit(
        total_chi2(None),
        nused,
        g2.shape[0] * (order + 1),
        smooth_order=order,
        masked_channels=masked,
    )
    if grid.size < 3:
        return null, null
    scan = _RippleScan(freqs, g2, s2, order)
    chis = np.array([scan(t * 1e-9) for t in grid])
    i = int(np.argmin(chis))
    fine = np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 41)
    fchis = np.array([scan(t * 1e-9) for t in fine])
    j = int(np.argmin(fchis))
    tau = float(fine[j])
    inside = fine[fchis <= fchis[j] + 1.0]
    sig_tau = max(float(inside.max() - inside.min()) / 2, float(fine[1] - fine[0]))
    # the phase is referred to nu = 0: its marginal error includes the delay's
    nu_mean = float(np.mean(freqs))
    feeds = []
    for g, s in rows:
        _, coef, cov = _bandpass_chi2(freqs, g, s, order, tau * 1e-9)
        c, sn = coef[-2], coef[-1]
        a = float(np.hypot(c, sn))
        ccs = cov[-2:, -2:]
        grad_a = np.array([c, sn]) / max(a, 1e-300)
        grad_p = np.array([sn, -c]) / max(a, 1e-300) ** 2
        feeds.append(
            {
                "a": a,
                "sigma_a": float(np.sqrt(abs(grad_a @ ccs @ grad_a))),
                "phi": float(np.arctan2(-sn, c)),
                "sigma_phi": float(
                    np.hypot(
                        np.sqrt(abs(grad_p @ ccs @ grad_p)), 2 * np.pi * nu_mean * sig_tau * 1e-9
                    )
                ),
            }
        )
    rip = BandpassFit(
        float(fchis[j]),
        null.nfreq,
        null.nparam + 2 * g2.shape[0] + 1,
        feeds[0]["a"],
        feeds[0]["sigma_a"],
        tau,
        sig_tau,
        feeds[0]["phi"],
        feeds[0]["sigma_phi"],
        per_feed=tuple(feeds),
        at_edge=bool(tau - tau_range_ns[0] < resolution or hi - tau < resolution),
        smooth_order=order,
        masked_channels=masked,
    )
    return null, rip


# gap metrics ----------------------------------------------------------------------------


def gap_metrics(
    fit: ExtendedFit,
    obs: Observation,
    tpl: SkyTemplates,
    bandpass: BandpassFit | None = None,
    n_time_modes: int = 4,
) -> dict[str, Any]:
    """Measure the disagreement between a fit and the data.

    One pass over the residuals, a chunk of antennas at a time (:meth:`ExtendedFit.
    residual_chunks`): every metric is a sum over antennas.

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``reduced_chi2``, ``rms_normalised_residual``,
        ``integration_jitter`` (rms over integrations of the channel-summed normalised
        residual / sqrt(channels): ~1 for white noise, >> 1 when whole integrations
        move together, e.g. broadband gain fluctuations), ``time_mode_power`` (mean
        over channels of the squared projection of the normalised residuals on
        ``P_0..P_{m-1}`` of LST, ~1 each when white),
        ``residual_delay_power`` (max and its delay of the time-averaged residual power
        spectrum along frequency, ~1 when white), ``delay_peak_G`` / ``delay_peak_Trxr``
        (largest delay-spectrum amplitude beyond 100 ns, mean removed),
        ``template_correlation`` (Pearson r of the residuals with Tsky, its Galactic part
        and the ground fraction), ``bandpass_reduced_chi2``.
    """
    basis = time_basis(obs.lsts, n_time_modes - 1)
    basis = np.vstack([np.ones(obs.ntime), basis]) if basis.size else np.ones((1, obs.ntime))
    norm = basis / np.sqrt((basis**2).sum(axis=1, keepdims=True))
    fb = np.broadcast_to(tpl.f_below[:, None, :], tpl.total.shape)
    templates = {"tsky": tpl.total, "galactic": tpl.galactic, "ground_fraction": fb}
    mode_power = np.zeros(norm.shape[0])
    nchan = 0
    ps_sum = np.zeros(obs.nfreq // 2 + 1)
    nspectra = 0
    nused_total, sum_r, sum_r2 = 0, 0.0, 0.0
    jitter_sum, nint = 0.0, 0
    count = np.zeros(tpl.total.shape)  # antennas with a usable sample, (P, T, F)
    sum_tr = dict.fromkeys(templates, 0.0)
    for _, res in _residual_pieces(fit):
        ok = np.isfinite(res)
        r0 = np.where(ok, res, 0.0)
        proj = np.einsum("kt,aptf->apfk", norm, r0)
        mode_power += (proj**2).reshape(-1, proj.shape[-1]).sum(axis=0)
        nchan += proj.size // proj.shape[-1]
        ps = np.abs(np.fft.rfft(r0, axis=-1)) ** 2 / obs.nfreq
        ps_sum += ps.reshape(-1, ps.shape[-1]).sum(axis=0)
        nspectra += ps.size // ps.shape[-1]
        nused_total += int(ok.sum())
        sum_r += float(r0.sum())
        sum_r2 += float((r0**2).sum())
        nused = ok.sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            per_int = r0.sum(axis=-1) / np.sqrt(nused)
        jitter_sum += float((per_int[nused > 0] ** 2).sum())
        nint += int((nused > 0).sum())
        count += ok.sum(axis=0)
        for name, t in templates.items():
            sum_tr[name] += float(np.einsum("aptf,ptf->", r0, t))
    ps_mean = ps_sum / max(nspectra, 1)
    delays = np.fft.rfftfreq(obs.nfreq, d=obs.freqs[1] - obs.freqs[0]) * 1e9
    k = int(np.argmax(ps_mean[1:]) + 1)
    n = max(nused_total, 1)

    def peak(values: np.ndarray) -> dict[str, float]:
        try:
            ds = delay_spectrum(values.reshape(-1, obs.nfreq), obs.freqs, subtract_mean=True)
        except ValueError:
            return {"amplitude": float("nan"), "delay_ns": float("nan")}
        sel = ds.delays_ns > 100
        amp = np.nanmax(ds.amplitude[:, sel], axis=0)
        i = int(np.nanargmax(amp))
        return {"amplitude": float(amp[i]), "delay_ns": float(ds.delays_ns[sel][i])}

    def corr(name: str) -> float:
        # Pearson r over the usable samples; the template is shared by all antennas, so its
        # moments are weighted by the number of antennas with a usable sample
        t = np.asarray(templates[name], float)
        seen = count > 0
        if not seen.any() or np.ptp(t[seen]) == 0:
            return 0.0
        t_mean = float((count * t).sum()) / n
        var_t = float((count * (t - t_mean) ** 2).sum())
        r_mean = sum_r / n
        var_r = sum_r2 - n * r_mean**2
        cov = sum_tr[name] - t_mean * sum_r
        return float(cov / math.sqrt(var_t * var_r)) if var_t > 0 and var_r > 0 else 0.0

    return {
        "chi2": fit.chi2,
        "dof": fit.dof,
        "reduced_chi2": fit.reduced_chi2,
        "rms_normalised_residual": float(np.sqrt(sum_r2 / n)),
        "integration_jitter": float(np.sqrt(jitter_sum / nint)) if nint else 0.0,
        "time_mode_power": [float(v) for v in mode_power / max(nchan, 1)],
        "residual_delay_power": {"max": float(ps_mean[k]), "delay_ns": float(delays[k])},
        "delay_peak_G": peak(fit.G),
        "delay_peak_Trxr": peak(fit.Trxr),
        "template_correlation": {name: corr(name) for name in templates},
        "bandpass_reduced_chi2": None if bandpass is None else bandpass.reduced_chi2,
    }


# the diagnosis --------------------------------------------------------------------------


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes
    ----------
    steps
        One dict per accepted step: ``name``, ``parameters`` ``{p: {value, sigma}}``,
        ``statistic`` (Delta BIC), ``delta`` (Delta chi^2), ``gap_before``,
        ``gap_after``, ``candidates`` (every candidate's Delta BIC).
    effects
        Names of the accepted effects, in order.
    initial_gap, final_gap
        Gap metrics of the starting and final models.
    identifiability
        ``{effect: fraction of Fisher information not absorbed by (G, n)}`` at the start
        (0: below :data:`IDENTIFIABLE_RESOLUTION`, degenerate with ``(G, n)``).
    config
        Statistic, threshold, prior and settings.
    residual_snapshots
        ``[(label, (Ntime, Nfreq) normalised residuals of antenna 0, pol 0)]``.
    product_change
        How the calibration products change from the starting model to the diagnosed one
        (:func:`product_impact`); each step has its own under ``product_impact``.
    unexplained
        ``None`` when the final model fits to within the noise; else what remains and its
        structure (:func:`describe_unexplained`): no catalogue entry explains it.
    negligible
        Effects detected (significant by the same test, kept in the fitted model) whose
        impact on ``G`` and ``Trxr`` is negligible (:func:`is_negligible`): reported as
        "detected, negligible", not named among :attr:`effects`; their steps say
        ``negligible: true``.
    """

    steps: list[dict[str, Any]] = field(default_factory=list)
    effects: list[str] = field(default_factory=list)
    initial_gap: dict[str, Any] = field(default_factory=dict)
    final_gap: dict[str, Any] = field(default_factory=dict)
    identifiability: dict[str, float] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    residual_snapshots: list[tuple[str, np.ndarray]] = field(default_factory=list, repr=False)
    final_fit: ExtendedFit | None = field(default=None, repr=False)
    final_parameters: dict[str, dict[str, Any]] = field(default_factory=dict)
    product_change: dict[str, Any] = field(default_factory=dict)
    unexplained: dict[str, Any] | None = None
    negligible: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (without residual arrays)."""
        return {
            "effects": self.effects,
            "negligible": self.negligible,
            "unexplained": self.unexplained,
            "steps": self.steps,
            "initial_gap": self.initial_gap,
            "final_gap": self.final_gap,
            "identifiability": self.identifiability,
            "final_parameters": self.final_parameters,
            "product_change": self.product_change,
            "config": self.config,
        }


#: Largest |parameter| of an effect taken as that effect (fractions; K for ``sky_offset`` and
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
#: Legendre order of the smooth part removed from a ``gain_jitter`` series before its
#: remainder is tested (:func:`jitter_is_significant`).
JITTER_SMOOTH_ORDER = 3
#: Sidereal-day harmonics also removed from a ``gain_jitter`` series spanning at least
#: :data:`autocal.diagnosis.effects.DIURNAL_MIN_SPAN_H` (:func:`jitter_is_significant`).
JITTER_DIURNAL_HARMONICS = 2


def jitter_is_significant(
    eps: np.ndarray,
    sigma: np.ndarray,
    lsts: np.ndarray,
    sky_shapes: np.ndarray | None = None,
    *,
    ndata: int = 1,
    overdispersion: float = 1.0,
) -> tuple[bool, dict[str, float]]:
    """Test whether a per-integration gain series is jitter rather than a smooth change.

    A ``gain_jitter`` fit absorbs any achromatic time structure, including a smooth one
    (a drift) and the time shape of a sky model that is slightly wrong (the series then
    follows the sky's own variation). The series counts as jitter only if, after removing
    a Legendre polynomial of order :data:`JITTER_SMOOTH_ORDER` in LST and the sky's time
    shapes (``sky_shapes``: e.g. the band-averaged model Tsky, its square and its time
    derivative), and over 6 h or more :data:`JITTER_DIURNAL_HARMONICS` sidereal-day
    harmonics, the remainder pays for its extra parameters as any candidate must: its
    chi-square over the overdispersion, less ``ln N`` per parameter beyond the smooth part,
    exceeds :data:`BIC_THRESHOLD`. Fluctuations correlated from one integration to the
    next (red gain noise) pass when they are large; what a smooth function of time or of the
    sky explains does not, and goes to a smooth effect or stays unexplained.

    Parameters
    ----------
    eps
        ``(Ntime,)`` fractional gain factors (0 for the reference integration).
    sigma
        ``(Ntime,)`` their 1-sigma (0 for the reference: it gets the median).
    lsts
        ``(Ntime,)`` hours.
    sky_shapes
        ``(K, Ntime)`` further smooth templates, or ``None``.
    ndata, overdispersion
        The data count ``N`` of the BIC penalty and the fit's ``max(1, chi^2/dof)``.

    Returns
    -------
    bool, dict
        The verdict and the numbers behind it (``rough_reduced_chi2``, ``rough_delta_bic``,
        and for information ``smooth_fraction``, the share of the series' weighted power the
        smooth part holds, and ``lag1``, the remainder's lag-1 autocorrelation).
    """
    eps = np.asarray(eps, float)
    sig = np.asarray(sigma, float)
    good = np.isfinite(eps) & np.isfinite(sig)
    positive = good & (sig > 0)
    sig = np.where(positive, sig, np.median(sig[positive]) if positive.any() else 1.0)
    eps = np.where(good, eps, 0.0)
    rows = [np.ones(eps.size)]
    order = min(JITTER_SMOOTH_ORDER, max(int(good.sum()) - 3, 0))
    if order:
        rows += list(time_basis(lsts, order))
    if np.ptp(unwrap_lsts(np.asarray(lsts, float))) >= DIURNAL_MIN_SPAN_H:
        # the catalogue's diurnal drifts are smooth too (a sidereal-day sine is not a
        # low-order polynomial over a day)
        rows += list(diurnal_basis(lsts, JITTER_DIURNAL_HARMONICS))
    if sky_shapes is not None:
        for shape in np.atleast_2d(sky_shapes):
            if np.all(np.isfinite(shape)) and np.ptp(shape) > 0:
                rows.append((shape - shape.mean()) / np.ptp(shape))
    basis = np.vstack(rows)
    basis = basis[: max(1, min(basis.shape[0], int(good.sum()) - 2))]
    w = good / sig**2
    coef = np.linalg.lstsq((basis * np.sqrt(w)).T, eps * np.sqrt(w), rcond=None)[0]
    rough = np.where(good, eps - coef @ basis, 0.0)
    dof = max(int(good.sum()) - basis.shape[0], 1)
    chi2 = float(np.sum(w * rough**2))
    z = rough[good] / sig[good]
    lag1 = float(np.sum(z[1:] * z[:-1]) / np.sum(z * z)) if z.size > 2 and np.any(z) else 0.0
    centred = np.where(good, eps - np.sum(w * eps) / np.sum(w), 0.0)
    total_power = float(np.sum(w * centred**2))
    info = {
        "rough_reduced_chi2": chi2 / dof,
        "smooth_fraction": 1.0 - chi2 / total_power if total_power > 0 else 0.0,
        "lag1": lag1,
    }
    # the per-integration freedom beyond the smooth part must pay for itself as any
    # candidate does: Delta BIC of the rough part (its chi2 over the overdispersion, less
    # ln N per extra parameter) above the threshold
    info["rough_delta_bic"] = chi2 / max(overdispersion, 1.0) - dof * math.log(max(ndata, 2))
    return bool(info["rough_delta_bic"] > BIC_THRESHOLD), info


#: Median of a chi-square variable with one degree of freedom.
_CHI2_1_MEDIAN = float(stats.chi2.ppf(0.5, 1))


def robust_overdispersion(fit: ExtendedFit) -> float:
    """Return the fit's overdispersion from the median squared normalised residual.

    ``median(r^2) / 0.455`` (the median of chi-square with one degree of freedom): the
    scatter of the bulk of the data, which a few strong outliers (RFI not yet flagged, on
    the first search) do not inflate as they inflate ``chi^2 / dof``. Used by the
    ``gain_jitter`` test, whose verdict would otherwise rest on the RFI.
    """
    squares = []
    for _, res in _residual_pieces(fit):
        flat = np.asarray(res).ravel()
        # a whole HERA file has 2e8 residuals: a regular subsample of ~4e6 is plenty
        stride = max(1, flat.size * max(1, fit_nchunks(fit)) // ROBUST_SAMPLES)
        while stride > 1 and math.gcd(stride, np.shape(res)[-1]) != 1:
            stride += 1  # not a comb of the same channels
        sub = flat[::stride]
        squares.append(sub[np.isfinite(sub)] ** 2)
    values = np.concatenate(squares) if squares else np.zeros(0)
    if not values.size:
        return fit.reduced_chi2
    return float(np.median(values) / _CHI2_1_MEDIAN)


#: Residuals :func:`robust_overdispersion` takes the median of, at most (about).
ROBUST_SAMPLES = 1 << 22


def fit_nchunks(fit: Any) -> int:
    """Return the number of antenna chunks a fit streams its residuals in (1 for arrays)."""
    source = getattr(fit, "source", None)
    return len(source.chunks) if source is not None else 1


def sky_time_shapes(tpl: SkyTemplates) -> np.ndarray:
    """Return ``(3, Ntime)`` time shapes of the model sky.

    The band-averaged relative Tsky, its square and its time derivative: the templates a
    slightly wrong sky model leaves in a per-integration gain series.
    """
    rel = tpl.total / np.mean(tpl.total, axis=1, keepdims=True)  # (P, T, F)
    mean = rel.mean(axis=(0, 2))
    deriv = np.gradient(mean)
    return np.vstack([mean, mean**2, deriv])


#: The final model's chi-square may exceed its degrees of freedom by this many standard
#: deviations (``sqrt(2 dof)``) before the remainder is reported as unexplained.
UNEXPLAINED_SIGMAS = 5.0


def describe_unexplained(
    fit: ExtendedFit, obs: Observation, gap: dict[str, Any]
) -> dict[str, Any] | None:
    """Describe the residual no catalogue entry explained, or ``None`` if there is none.

    Parameters
    ----------
    fit
        The final model's fit.
    obs
        The observation.
    gap
        The final model's :func:`gap_metrics`.

    Returns
    -------
    dict or None
        ``reduced_chi2``, ``excess_sigma`` (``(chi2 - dof) / sqrt(2 dof)``), the
        structure: ``time`` (``smooth`` when the low Legendre modes of LST carry most of
        it, ``integration to integration`` when whole integrations move together, else
        ``unstructured``), ``frequency`` (the delay of the residual's largest delay power
        and that power over white), ``antennas`` (reduced chi2 per antenna-pol, worst
        first) and ``message``.
    """
    dof = max(int(gap["dof"]), 1)
    excess = (gap["chi2"] - dof) / math.sqrt(2.0 * dof)
    if excess <= UNEXPLAINED_SIGMAS:
        return None
    modes = gap["time_mode_power"]
    jitter = gap["integration_jitter"]
    smooth = max(modes[1:], default=1.0)
    if smooth > max(4.0, jitter**2):
        time_kind = "smooth in time"
    elif jitter > 2.0:
        time_kind = "integration to integration (whole integrations move together)"
    else:
        time_kind = "unstructured in time"
    delay = gap["residual_delay_power"]
    freq_kind = (
        f"structured in frequency (delay power {delay['max']:.3g} x white at "
        f"{delay['delay_ns']:.0f} ns)"
        if delay["max"] > 4.0
        else "white in frequency"
    )
    per_feed = np.zeros((len(obs.antennas), len(obs.pols)))
    for sl, res in _residual_pieces(fit):
        ok = np.isfinite(res)
        per_feed[sl] = (np.where(ok, res, 0.0) ** 2).sum(axis=(2, 3)) / np.maximum(
            ok.sum(axis=(2, 3)), 1
        )
    feeds = sorted(
        (
            (float(per_feed[ia, ip]), int(a), str(p))
            for ia, a in enumerate(obs.antennas)
            for ip, p in enumerate(obs.pols)
        ),
        reverse=True,
    )
    antennas = [{"antenna": a, "pol": p, "reduced_chi2": v} for v, a, p in feeds]
    worst = ", ".join(f"{e['antenna']} {e['pol']} ({e['reduced_chi2']:.3g})" for e in antennas[:3])
    return {
        "reduced_chi2": float(gap["reduced_chi2"]),
        "excess_sigma": float(excess),
        "time": time_kind,
        "time_mode_power": modes,
        "integration_jitter": jitter,
        "frequency": freq_kind,
        "antennas": antennas,
        "message": (
            f"unexplained: chi2/dof {gap['reduced_chi2']:.4g} remains ({excess:.3g} sigma above "
            f"the noise) with no catalogue entry significant; the residual is {time_kind}, "
            f"{freq_kind}; largest in {worst}"
        ),
    }


#: An effect is negligible when it moves ``G`` and ``Trxr`` by less than this many total
#: sigma in the median channel ...
NEGLIGIBLE_MEDIAN_SIGMA = 0.1
#: ... and by less than this many in every channel.
NEGLIGIBLE_MAX_SIGMA = 1.0


#: ... or, whatever the errors, when the median channel's ``G`` moves by less than this
#: fraction and its ``Trxr`` by less than :data:`NEGLIGIBLE_TRXR_K`: below what the sky model
#: supports (autocal's Tsky and an independent forward model agree to 1e-4 to 1e-3,
#: ``tests/test_independent_sim.py``; a long clean observation has statistical errors
#: smaller than that).
NEGLIGIBLE_G_FRACTION = 1e-3
#: See :data:`NEGLIGIBLE_G_FRACTION` (kelvin).
NEGLIGIBLE_TRXR_K = 1.0


#: An effect whose Delta chi^2 exceeds this share of the data count (it removes more than
#: a tenth of the noise variance per sample) is a substantial feature of the data and never
#: "negligible", however little it moves the products (a clock 87 s off over a day takes
#: chi^2/dof from 8.5 to 1.0 and moves G by 6e-4 total sigma).
NEGLIGIBLE_MAX_CHI2_SHARE = 0.1


def is_negligible(impact: dict[str, Any], chi2_share: float = 0.0) -> bool:
    """Return whether a :func:`product_impact` is too small to matter for the products.

    Negligible: below :data:`NEGLIGIBLE_MEDIAN_SIGMA` total sigma in the median channel and
    :data:`NEGLIGIBLE_MAX_SIGMA` in every channel, for both ``G`` and ``Trxr``; or a median
    absolute change below :data:`NEGLIGIBLE_G_FRACTION` of ``G`` and
    :data:`NEGLIGIBLE_TRXR_K` in ``Trxr`` (below what the sky model itself supports) and
    no channel moving by ten times that. In both cases the products' variation in time
    must also stay put (``G_time``, ``Trxr_time``: a drift or jitter changing ``G(t)`` by
    more than :data:`NEGLIGIBLE_G_FRACTION` rms or ten times that at any integration, or
    ``Trxr(t)`` by :data:`NEGLIGIBLE_TRXR_K` in the median channel, matters to whoever
    applies the gains per integration, however well the time-mean products agree). Never
    negligible when fewer than half of the channels could be compared (the ordinary
    calibration failed in the rest). Never negligible either when the effect's
    ``chi2_share`` (its Delta chi^2 over the number of data) exceeds
    :data:`NEGLIGIBLE_MAX_CHI2_SHARE`.
    """
    if chi2_share > NEGLIGIBLE_MAX_CHI2_SHARE:
        return False
    g, t = impact.get("G", {}), impact.get("Trxr", {})
    if "median_change_over_sigma" not in g or "median_change_over_sigma" not in t:
        return False
    if any(e["channels"] < 0.5 * e.get("of", e["channels"]) for e in (g, t)):
        return False  # the yardstick calibration failed in most channels: no verdict
    small = (
        g.get("median_abs_relative_change", np.inf) < NEGLIGIBLE_G_FRACTION
        and t.get("median_abs_change_K", np.inf) < NEGLIGIBLE_TRXR_K
        and g.get("max_abs_relative_change", np.inf) < 10 * NEGLIGIBLE_G_FRACTION
        and t.get("max_abs_change_K", np.inf) < 10 * NEGLIGIBLE_TRXR_K
    )
    within = all(
        e["median_change_over_sigma"] < NEGLIGIBLE_MEDIAN_SIGMA
        and e["max_change_over_sigma"] < NEGLIGIBLE_MAX_SIGMA
        for e in (g, t)
    )
    gt, tt = impact.get("G_time", {}), impact.get("Trxr_time", {})
    steady = (
        gt.get("rms_relative_change", 0.0) < NEGLIGIBLE_G_FRACTION
        and gt.get("max_abs_relative_change", 0.0) < 10 * NEGLIGIBLE_G_FRACTION
        and tt.get("median_max_abs_change_K", 0.0) < NEGLIGIBLE_TRXR_K
        and tt.get("max_abs_change_K", 0.0) < 10 * NEGLIGIBLE_TRXR_K
    )
    return bool((small or within) and steady)


def product_sigmas(
    obs: Observation, tpl: SkyTemplates, prior: tuple[Any, Any] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return the total 1-sigma of ``G`` and ``Trxr`` of the ordinary calibration.

    The constant-model fit of :func:`autocal.fit.passes.fit` against the model Tsky, with
    radiometer weights, errors inflated by ``max(1, chi^2/dof)``, the total uncertainty
    (:mod:`autocal.fit.total_uncertainty`) and the diagnosis's receiver prior ``(trxr, sigma)`` if
    any: the yardstick of :func:`product_impact`. Every channel is fitted on its own, so a
    large observation is fitted :data:`PRODUCT_SIGMA_SAMPLES` at a time (the fit holds a
    few float64 copies of what it is given).
    """
    from autocal.fit.passes import fit

    per_antenna = math.prod(obs.shape[1:])
    chunks = antenna_chunks(obs.shape, max(1, PRODUCT_SIGMA_SAMPLES // per_antenna))
    if len(chunks) == 1:
        sol = fit(obs, tpl.total, scale_covariance="inflate", trxr_prior=prior)
        return sol.sigma_G, sol.sigma_Trxr
    shape3 = (obs.nant, len(obs.pols), obs.nfreq)
    sigma_g, sigma_t = np.empty(shape3), np.empty(shape3)
    for sl in chunks:
        part = obs.select(antennas=[int(a) for a in obs.antennas[sl]])
        part_prior = (
            None
            if prior is None
            else tuple(np.broadcast_to(np.asarray(v, float), shape3)[sl] for v in prior)
        )
        sol = fit(part, tpl.total, scale_covariance="inflate", trxr_prior=part_prior)
        sigma_g[sl], sigma_t[sl] = sol.sigma_G, sol.sigma_Trxr
    return sigma_g, sigma_t


def product_impact(
    before: ExtendedFit, after: ExtendedFit, sigma_g: np.ndarray, sigma_t: np.ndarray
) -> dict[str, Any]:
    """Return how ``G`` and ``Trxr`` move between two models, against the total errors.

    Parameters
    ----------
    before, after
        Fits without and with the effect(s).
    sigma_g, sigma_t
        ``(Nant, Npol, Nfreq)`` total 1-sigma of ``G`` and ``Trxr`` (:func:`product_sigmas`).

    Returns
    -------
    dict
        For ``G`` and ``Trxr``: the median and largest ``|change| / sigma`` over channels,
        the median change (relative for ``G``, kelvin for ``Trxr``) and the channels
        compared (time means: a jitter's ``G`` is its reference integration's);
        ``significant`` when the median change exceeds one total sigma. ``G_time``: the rms
        and largest change of ``G(t) / <G>`` (achromatic); ``Trxr_time``: the largest
        change over time of ``Trxr(t) - <Trxr>`` in kelvin, median channel and worst.
    """
    out: dict[str, Any] = {}
    gs_b, ns_b = _time_shapes(before)
    gs_a, ns_a = _time_shapes(after)
    with np.errstate(invalid="ignore", divide="ignore"):
        # the time-mean products (a jitter's G is that of its reference integration)
        g_b, g_a = (
            before.G * _mean_factor(before.gain_factor),
            after.G * _mean_factor(after.gain_factor),
        )
        t_b, t_a = (
            before.Trxr * _mean_factor(before.noise_factor),
            after.Trxr * _mean_factor(after.noise_factor),
        )
        pairs = {
            "G": (g_a - g_b, sigma_g, (g_a - g_b) / np.abs(g_b)),
            "Trxr": (t_a - t_b, sigma_t, t_a - t_b),
        }
        for name, (diff, sig, change) in pairs.items():
            z = np.abs(diff) / sig
            ok = np.isfinite(z) & np.isfinite(change)
            entry: dict[str, Any] = {"channels": int(ok.sum()), "of": int(z.size)}
            if ok.any():
                entry["median_change_over_sigma"] = float(np.median(z[ok]))
                entry["max_change_over_sigma"] = float(np.max(z[ok]))
                key = "median_relative_change" if name == "G" else "median_change_K"
                entry[key] = float(np.median(change[ok]))
                entry[key.replace("median_", "median_abs_")] = float(np.median(np.abs(change[ok])))
                entry[key.replace("median_", "max_abs_")] = float(np.max(np.abs(change[ok])))
            out[name] = entry
        # how the products' variation in time changes (drifts, jitter): G's relative
        # shape is achromatic; Trxr's in kelvin per channel
        dshape = gs_a - gs_b
        out["G_time"] = {
            "rms_relative_change": float(np.sqrt(np.mean(dshape**2))),
            "max_abs_relative_change": float(np.max(np.abs(dshape))),
        }
        # the largest change over time, one integration at a time (a whole HERA file's
        # (A, P, F, T) temporaries would be 1.6 GB each)
        ua, vb = np.broadcast_arrays(ns_a - 1.0, ns_b - 1.0)
        dtrx = np.zeros(np.shape(t_a))
        for u, v in zip(np.atleast_1d(ua), np.atleast_1d(vb), strict=True):
            np.fmax(dtrx, np.abs(t_a * u - t_b * v), out=dtrx)
        dtrx = np.where(np.isfinite(t_a) & np.isfinite(t_b), dtrx, np.nan)
        ok = np.isfinite(dtrx)
        out["Trxr_time"] = (
            {
                "median_max_abs_change_K": float(np.median(dtrx[ok])),
                "max_abs_change_K": float(np.max(dtrx[ok])),
            }
            if ok.any()
            else {}
        )
    medians = [e.get("median_change_over_sigma", 0.0) for e in (out["G"], out["Trxr"])]
    out["significant"] = bool(max(medians) > 1.0)
    return out


def _mean_factor(factor: np.ndarray | None) -> float:
    """Time mean of a fit's gain or noise factor (1 without one)."""
    return 1.0 if factor is None else float(np.mean(factor))


def _time_shapes(fit: ExtendedFit) -> tuple[np.ndarray, np.ndarray]:
    """``(Ntime,)`` gain and noise factors relative to their time means."""
    shapes = []
    for factor in (fit.gain_factor, fit.noise_factor):
        f = np.ones(1) if factor is None else np.asarray(factor, float)
        shapes.append(f / np.mean(f))
    return shapes[0], shapes[1]


def _params_dict(eff: Effect, fit: ExtendedFit) -> dict[str, dict[str, float]]:
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


@_blas_single_thread
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
        Candidate effects (default :func:`autocal.diagnosis.effects.catalogue`).
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
        :func:`auto_smooth_order`).
    flag_rfi
        Flag narrow-band and impulsive outliers (:func:`flag_outliers`) in the residuals
        of the starting model before anything is fitted (recorded in
        ``config["outlier_flagging"]``).
    outlier_threshold
        Robust sigmas beyond which a sample is an outlier.
    progress
        Called with ``(fraction, message)`` before every model fit (fraction in [0, 1],
        non-decreasing). It may raise to abandon the search (the service's cancellation);
        the exception propagates and nothing is returned.

    Returns
    -------
    Diagnosis
        Steps, accepted effects and gaps.
    """
    searches = 1 + (_OUTLIER_ROUNDS if flag_rfi else 0)
    search = 0

    def report(fraction: float, message: str) -> None:
        if progress is not None:
            progress(min(1.0, (search + fraction) / searches), f"search {search + 1}: {message}")

    kwargs: dict[str, Any] = {
        "candidates": candidates,
        "trxr_prior": trxr_prior,
        "trxr_prior_sigma": trxr_prior_sigma,
        "bic_threshold": bic_threshold,
        "alpha": alpha,
        "max_steps": max_steps,
        "smooth_order": smooth_order,
        "progress": report,
    }
    nflag0 = int(obs.flags.sum())
    diag = _diagnose_once(obs, tpl, **kwargs)
    rounds = 0
    # outliers are judged on the residuals of the *final* model, so that structure an
    # effect explains is never mistaken for RFI; then the search is repeated without them
    while flag_rfi and rounds < _OUTLIER_ROUNDS and diag.final_fit is not None:
        search += 1
        flags = flag_outliers(obs, diag.final_fit, threshold=outlier_threshold)
        if int(flags.sum()) == int(obs.flags.sum()):
            break
        obs = dataclasses.replace(obs, flags=flags)
        rounds += 1
        logger.info(
            "flagged %d outlier samples (%.2f %% of the data); searching again",
            int(obs.flags.sum()) - nflag0,
            100 * (obs.flags.sum() - nflag0) / obs.flags.size,
        )
        diag = _diagnose_once(obs, tpl, **kwargs)
    diag.config["outlier_flagging"] = {
        "enabled": flag_rfi,
        "threshold_robust_sigma": outlier_threshold,
        "rounds": rounds,
        "samples_flagged": int(obs.flags.sum()) - nflag0,
        "fraction_flagged": float(obs.flags.mean()),
        "channels_fully_flagged": int(obs.flags.all(axis=2).sum()),
    }
    return diag


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


def _retest_accepted(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    current: ExtendedFit,
    w: np.ndarray,
    prior_kw: dict[str, Any],
    bic_threshold: float,
    diag: Diagnosis,
    when: str,
    keep: Effect | None = None,
) -> tuple[list[Effect], ExtendedFit]:
    """Drop accepted effects that the others now explain (backward elimination).

    An effect accepted early may be explained away by later ones (a per-integration gain
    soaking up part of a sky error, say): any whose removal from the current model no
    longer costs Delta BIC > ``bic_threshold`` is dropped, one at a time, the model refitted
    after each. ``keep`` (the effect just accepted) is not re-tested.
    """
    changed = True
    while changed and len(active) > 1:
        changed = False
        chat_f = max(1.0, current.reduced_chi2)
        for eff in list(active):
            if eff is keep:
                continue
            rest = [a for a in active if a is not eff]
            try:
                without = fit_extended(obs, tpl, rest, weights=w, start=current.params, **prior_kw)
            except (DiagnoseError, np.linalg.LinAlgError):
                continue
            stat = (without.chi2 - current.chi2) / chat_f - eff.nfree * math.log(current.ndata)
            if stat < bic_threshold:
                logger.info("re-test at %s: %s dropped (Delta BIC %.1f)", when, eff.name, stat)
                active = rest
                for names in (diag.effects, diag.negligible):
                    if eff.name in names:
                        names.remove(eff.name)
                for st in diag.steps:
                    if st["name"] == eff.name and "dropped_in_backward_pass" not in st:
                        st["dropped_in_backward_pass"] = {"statistic": float(stat), "at": when}
                current = fit_extended(
                    obs, tpl, active, weights=w, start=without.params, **prior_kw
                )
                changed = True
                break
    return active, current


#: A candidate is refused on its own parameters only when their (diagonal) Wald
#: statistic is below this fraction of its Delta chi2 (:func:`wald_statistic`).
WALD_SHORTFALL = 0.5


def wald_statistic(fit: ExtendedFit, eff: Effect) -> float | None:
    """Return ``sum (value / sigma)^2`` of an effect's free parameters in a fit.

    The Wald statistic with the covariance's diagonal: for a model linear in the effect's
    parameters it equals the fit's Delta chi2 when the parameters are uncorrelated. A
    Delta chi2 far above it means the improvement came from the other parameters moving
    (the model is not linear in them), not from this effect. ``None`` for a fixed effect.
    """
    if eff.fixed is not None or not eff.nfree or eff.name not in fit.params:
        return None
    values = np.asarray(fit.params[eff.name], float)
    sigmas = np.asarray(fit.sigmas[eff.name], float)
    ok = np.isfinite(values) & np.isfinite(sigmas) & (sigmas > 0)
    return float(np.sum((values[ok] / sigmas[ok]) ** 2))


#: Significance (chi-square survival probability) below which the two half-band fits of
#: an effect disagree (:func:`band_consistency`) ...
CONSISTENCY_ALPHA = 1e-3
#: ... provided they also differ by more than this fraction of the whole band's value.
CONSISTENCY_RELATIVE = 0.3


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
    sub_tpl = _template_subset(tpl, channels=channels)
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
) -> dict[str, Any] | None:
    """Fit a candidate in the lower and the upper half of the band and compare.

    Every effect of the catalogue has the same parameters at every frequency (an
    achromatic drift, one sky scale or index, one beam-width factor, one timing offset).
    A template that fits because it absorbs structure of another origin, e.g. a spectral
    index of -0.5 taking up part of a beam-shape error, generally gets different values
    from the two halves. They disagree when the difference is significant (chi-square of
    the difference over the summed variances, scaled by the halves' overdispersion,
    survival probability below :data:`CONSISTENCY_ALPHA`) and larger than
    :data:`CONSISTENCY_RELATIVE` of the whole band's value (a real effect measured with
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
    dict or None
        ``consistent``, ``values`` (lower, upper, whole), ``chi2``, ``k``, ``p_value``,
        ``relative_difference``, ``partner`` and ``message``; ``None`` (no verdict) when
        the candidate has no free parameters, is a per-integration series
        (``gain_jitter``, judged by :func:`jitter_is_significant`: split by band, its
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
        halves.append(half)
    out = _compare_halves(eff, halves, fit)
    if out is None:
        return None
    out["partner"] = None if partner is None else partner.name
    if partner is not None and partner.fixed is None and partner.nfree:
        other = _compare_halves(partner, halves, fit)
        if other is not None and not other["consistent"]:
            out["consistent"] = False
            out["message"] += f"; with {partner.name}: {other['message']}"
        elif partner is not None:
            out["message"] += f" (fitted with {partner.name})"
    return out


def _compare_halves(
    eff: Effect, halves: list[ExtendedFit], whole_fit: ExtendedFit
) -> dict[str, Any] | None:
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
    rel = float(np.linalg.norm((lo - hi)[ok]) / max(np.linalg.norm(whole[ok]), 1e-300))
    consistent = bool(pval >= CONSISTENCY_ALPHA or rel <= CONSISTENCY_RELATIVE)
    show = (
        f"{eff.params[0]} = {lo[0]:.4g} +- {slo[0]:.2g} (lower half), {hi[0]:.4g} +- "
        f"{shi[0]:.2g} (upper)"
        if lo.size <= 2
        else f"{k} values differ by {100 * rel:.0f} % rms of the whole band's"
    )
    return {
        "consistent": consistent,
        "values": {"lower": lo.tolist(), "upper": hi.tolist(), "whole": whole.tolist()}
        if lo.size <= 8
        else None,
        "chi2": chi2,
        "k": k,
        "p_value": pval,
        "relative_difference": rel,
        "message": f"{show}; chi2 {chi2:.3g} for {k}, p {pval:.2g}",
    }


#: Most partners tried for a candidate whose parameters the band's halves disagree on.
CONSISTENCY_PARTNERS = 3


def _consistent_with_partner(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    cand: tuple[Any, ...],
    results: list[tuple[Any, ...]],
    w: np.ndarray,
    prior_kw: dict[str, Any],
    bic_threshold: float,
    alpha: float,
    check: dict[str, Any],
) -> dict[str, Any]:
    """Re-test an inconsistent candidate with another significant candidate alongside.

    Two effects missing at once bias each other's half-band fits (a noise drift and a
    spectral index error are both chromatic); fitted together, both agree across the band.
    The next :data:`CONSISTENCY_PARTNERS` significant candidates of other names are tried;
    the first joint fit in which both are consistent is returned (with ``partner``), else
    the original ``check``.
    """
    eff, payload = cand[3], cand[4]
    own = payload[1] if isinstance(payload, tuple) else payload
    tried = 0
    for other in results:
        o_stat, o_dchi, o_k, o_eff, o_payload, o_chat = other
        if other is cand or o_eff.name == eff.name or o_eff.kind in ("bandpass", "feed_gain"):
            continue
        if not (
            o_stat > bic_threshold and float(stats.chi2.sf(o_dchi / o_chat, max(o_k, 1))) < alpha
        ):
            break
        if tried >= CONSISTENCY_PARTNERS:
            break
        tried += 1
        partner = o_payload[2] if isinstance(o_payload, tuple) else o_eff
        o_fit = o_payload[0] if isinstance(o_payload, tuple) else o_payload
        try:
            joint = fit_extended(
                obs,
                tpl,
                [*active, eff, partner],
                weights=w,
                start={**o_fit.params, **own.params},
                **prior_kw,
            )
        except (DiagnoseError, np.linalg.LinAlgError):
            continue
        again = band_consistency(obs, tpl, active, eff, joint, w, prior_kw, partner=partner)
        if again is not None and again["consistent"]:
            return again
    return check


#: Most antenna-pols for which ``antenna_gain_jitter`` is tried (one fit each).
FEED_JITTER_MAX_FEEDS = 64


@dataclass(frozen=True)
class FeedGainFit:
    """Every antenna-pol's own gain series (:func:`fit_feed_gains`).

    Attributes
    ----------
    factors, sigmas
        ``(Nant, Npol, Ntime)`` gain factors (time mean 1 per antenna-pol) and 1-sigma.
    chi2
        Sum of the antenna-pols' chi-square (with their prior terms).
    delta_chi2
        The common-series model's chi-square less :attr:`chi2`.
    k
        Extra parameters: ``(Nfeeds - 1) (Ntime - 1)`` for a jitter replacing the common
        series, ``Nfeeds x order`` for a drift.
    ndata, nparam
        Data (with prior rows) and parameters of the per-antenna-pol model.
    values
        ``(Nant, Npol, k)`` each antenna-pol's fitted parameters.
    """

    factors: np.ndarray
    sigmas: np.ndarray
    chi2: float
    delta_chi2: float
    k: int
    ndata: int
    nparam: int
    values: np.ndarray | None = None

    @property
    def reduced_chi2(self) -> float:
        """``chi^2 / dof``."""
        return self.chi2 / max(self.ndata - self.nparam, 1)


def fit_feed_gains(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    current: ExtendedFit,
    w: np.ndarray,
    prior_kw: dict[str, Any],
    eff: Effect,
) -> FeedGainFit | None:
    """Fit each antenna-pol's own gain series, the other effects held at their values.

    ``antenna_gain_jitter`` (``eff.basis == "feed_integration"``): the model with one
    common series (``gain_jitter`` in ``active``, fitted in ``current``) is nested in this
    one, each antenna-pol getting its own series started from the common one.
    ``antenna_gain_drift`` (``"feed_legendre"``): each antenna-pol its own Legendre drift
    of order ``eff.order`` on top of the current model. Every other accepted effect is
    fixed at its joint estimate, so the antenna-pols are independent and fitted one by
    one; an antenna-pol without usable data follows the shared series. ``None`` when there
    is nothing to test.

    Raises
    ------
    DiagnoseError
        When an antenna-pol cannot be fitted or some of its own parameters have no data.
    """
    jitter = next((a for a in active if a.basis == "integration"), None)
    if eff.basis == "feed_integration":
        if jitter is None:
            return None
        own = jitter
        start = {jitter.name: current.params[jitter.name]}
        replaced: Effect | None = jitter
        k_per_feed, k_shared = obs.ntime - 1, obs.ntime - 1
    else:
        own = Effect(eff.name, "gain", eff.params, eff.units, eff.order, basis="legendre")
        start, replaced = {}, None
        k_per_feed, k_shared = eff.order, 0
    held = [
        a if a.fixed is not None else dataclasses.replace(a, fixed=tuple(current.params[a.name]))
        for a in active
        if a is not replaced
    ]
    basis = own.time_basis(obs.lsts)
    shape = (obs.nant, len(obs.pols), obs.nfreq)
    prior = {
        key: value
        if value is None or np.ndim(value) == 0
        else np.broadcast_to(np.asarray(value, float), shape)
        for key, value in prior_kw.items()
    }
    factors = np.ones((obs.nant, len(obs.pols), obs.ntime))
    sigmas = np.zeros_like(factors)
    values = np.zeros((obs.nant, len(obs.pols), basis.shape[0]))
    chi2, ndata, nparam, skipped = 0.0, 0, 0, 0
    for ia, ant in enumerate(obs.antennas):
        for ip, pol in enumerate(obs.pols):
            sub = obs.select(antennas=[int(ant)], pols=[pol])
            usable = (~sub.flags & np.isfinite(sub.data)).sum(axis=2) >= 3
            if not usable.any():
                # no data: it follows the shared series and adds no parameter
                factors[ia, ip] = (
                    current.gain_factor / np.mean(current.gain_factor) if replaced else 1.0
                )
                skipped += 1
                continue
            sub_tpl = _template_subset(tpl, pols=slice(ip, ip + 1))
            sub_prior = {
                key: value
                if value is None or np.ndim(value) == 0
                else value[ia : ia + 1, ip : ip + 1]
                for key, value in prior.items()
            }
            try:
                fit = fit_extended(
                    sub,
                    sub_tpl,
                    [own, *held],
                    weights=w[ia : ia + 1, ip : ip + 1],
                    start=start,
                    **sub_prior,
                )
            except (DiagnoseError, np.linalg.LinAlgError) as exc:
                raise DiagnoseError(f"antenna {ant} {pol} could not be fitted: {exc}") from exc
            if fit.identifiable.get(own.name, 1.0) < MIN_IDENTIFIABLE:
                raise DiagnoseError(
                    f"antenna {ant} {pol}: some of its own parameters have no data (e.g. an "
                    "integration flagged for this antenna-pol only)"
                )
            values[ia, ip] = fit.params[own.name]
            factor = 1.0 + fit.params[own.name] @ basis
            factors[ia, ip] = factor / np.mean(factor)
            # 1-sigma of the factor at each integration (diagonal: the reference of a
            # series, or a drift's centre, has none)
            sigmas[ia, ip] = np.sqrt(fit.sigmas[own.name] ** 2 @ basis**2)
            chi2 += fit.chi2
            ndata += fit.ndata
            nparam += fit.nparam
    nfeeds = obs.nant * len(obs.pols)
    return FeedGainFit(
        factors=factors,
        sigmas=sigmas,
        chi2=chi2,
        delta_chi2=float(current.chi2 - chi2),
        k=(nfeeds - skipped) * k_per_feed - k_shared,
        ndata=ndata,
        nparam=nparam,
        values=values,
    )


def feed_departures_rough(
    feed: FeedGainFit, current: ExtendedFit, obs: Observation, tpl: SkyTemplates
) -> float:
    """Delta BIC of the rough part of each antenna-pol's departure from the common series.

    The test :func:`jitter_is_significant` applies to ``gain_jitter``, applied to every
    antenna-pol's series divided by the common one and summed over antenna-pols: what a
    smooth function of time explains (one antenna's gain drifting against the others) is
    not jitter.
    """
    shared = current.gain_factor / np.mean(current.gain_factor)
    shapes = sky_time_shapes(tpl)
    total = 0.0
    for ia in range(obs.nant):
        for ip in range(len(obs.pols)):
            _, info = jitter_is_significant(
                feed.factors[ia, ip] / shared - 1.0,
                feed.sigmas[ia, ip],
                obs.lsts,
                shapes,
                ndata=current.ndata,
                overdispersion=feed.reduced_chi2,
            )
            total += info["rough_delta_bic"]
    return float(total)


#: Common entries that a per-antenna entry contains (the antenna-pols sharing one series
#: or drift is a special case): named once the per-antenna one is accepted, they stay in
#: the fitted model (the part the antenna-pols share) but are reported as superseded.
SUPERSEDES = {
    "antenna_gain_jitter": ("gain_jitter", ("integration",)),
    "antenna_gain_drift": ("gain_drift", ("legendre",)),
}


def _supersede(diag: Diagnosis, accepted: set[str]) -> None:
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


def _template_subset(
    tpl: SkyTemplates, pols: slice = slice(None), channels: slice = slice(None)
) -> SkyTemplates:
    """Return the templates of some polarisations and channels."""
    fields: dict[str, Any] = {"freqs": tpl.freqs[channels]}
    for name in ("total", "galactic", "cmb", "ground", "beam_dwidth", "lst_derivative"):
        arr = getattr(tpl, name)
        fields[name] = None if arr is None else arr[pols, :, channels]
    for name in ("f_above", "f_below"):
        fields[name] = getattr(tpl, name)[pols, channels]
    if tpl.beam_width_poly is not None:
        fields["beam_width_poly"] = tpl.beam_width_poly[:, pols, :, channels]
    return dataclasses.replace(tpl, **fields)


#: Most times one search re-fits its model from a candidate's better minimum
#: (:func:`_escape_local_minimum`).
MAX_RESTARTS = 2


def _escape_local_minimum(
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
    ``None``. Every fit's prior weights come from the model without effects, so chi2 of
    fits started from different values compare.
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


#: A step of a large search fits in full at least this many time-domain candidates (those
#: with the best scores, :class:`_StepScreen`) ...
SCREEN_FITS = 2
#: ... and then every one whose score-based Delta BIC comes within this much of the best
#: fitted candidate's Delta BIC, or within :data:`SCREEN_FRACTION` of it if that is more.
SCREEN_MARGIN = BIC_THRESHOLD
#: See :data:`SCREEN_MARGIN`. The score misses the full fit's Delta chi^2 by < 1 % for the
#: candidates near the data's effect and overestimates it by up to 25 % for strong ones far
#: from it (``beam_width`` against a gain drift; the test of :func:`screen_candidates`).
SCREEN_FRACTION = 0.25


class _StepScreen:
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

    def skip(self, eff: Effect, results: list[tuple]) -> bool:
        """Return whether to skip the candidate given the step's results so far."""
        score = self.scores.get(id(eff))
        if score is None:
            return False
        label = f"{eff.name}/{eff.basis}{eff.order}"
        if score.identifiable < MIN_IDENTIFIABLE:
            self.diag.identifiability.setdefault(eff.name, score.identifiable)
            return True
        fitted = [r for r in results if r[3].kind != "bandpass"]
        if len(fitted) >= SCREEN_FITS:
            chat = max(1.0, min(r[5] for r in fitted))
            best = max(r[1] / chat - r[2] * self.lnn for r in fitted)
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


def _diagnose_once(
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
    progress: Callable[[float, str], None] = lambda fraction, message: None,
) -> Diagnosis:
    """One search for effects (:func:`diagnose` without the outlier flagging)."""
    width = obs.channel_width[None, None, None, :]
    tint = obs.integration_time[None, None, :, None]
    for sl in antenna_chunks(obs.shape):
        if not np.all((width * (tint * obs.nsamples[sl]))[~obs.flags[sl]] > 0):
            raise DiagnoseError(
                "diagnose needs radiometer weights: channel width, integration time"
            )
    cands = (
        list(candidates)
        if candidates is not None
        else catalogue(
            include_beam_width=tpl.beam_dwidth is not None,
            ntime=obs.ntime,
            include_timing=tpl.lst_derivative is not None,
            span_h=float(np.ptp(unwrap_lsts(obs.lsts))),
            nfeeds=obs.nant * len(obs.pols),
        )
    )
    if smooth_order is None:
        smooth_order = auto_smooth_order(obs.freqs, 90.0)
    prior_kw = {"trxr_prior": trxr_prior, "trxr_prior_sigma": trxr_prior_sigma}
    active: list[Effect] = []
    cable: tuple[BandpassFit, Effect] | None = None
    diag = Diagnosis(
        config={
            "statistic": "Delta BIC = Delta chi2 / c - k ln N (radiometer-weighted chi2; "
            "c = max(1, smallest chi2/dof among the step's candidate models), the "
            "overdispersion of a quasi-likelihood, so unmodelled excess scatter does not "
            "pass for evidence; "
            "cable_reflection: chi2 of fitted G(nu) vs smooth bandpass, N = Nfreq)",
            "bic_threshold": bic_threshold,
            "alpha": alpha,
            "trxr_prior_K": None if trxr_prior is None else _describe_values(trxr_prior),
            "trxr_prior_sigma_K": None
            if trxr_prior is None
            else _describe_values(trxr_prior_sigma),
            "smooth_bandpass_order": smooth_order,
            "min_identifiable": MIN_IDENTIFIABLE,
            "candidates": [c.describe() for c in cands],
        }
    )
    # weights from the model: two passes of the baseline, then outliers (RFI) flagged
    progress(0.0, "fitting the starting model")
    w = radiometer_weights(obs, obs.data)
    current = fit_extended(obs, tpl, active, weights=w, **prior_kw)
    w = radiometer_weights(obs, current)
    current = fit_extended(obs, tpl, active, weights=w, **prior_kw)
    base_fit = current.detached()  # its G and Trxr only: no reference to these weights
    if trxr_prior is not None:
        # one set of prior weights for every fit of the search (from the model without
        # effects), whatever effects a fit holds fixed: their chi2 compare
        prior_kw["gain_ref"] = base_fit.G
    sigma_g, sigma_t = product_sigmas(
        obs, tpl, None if trxr_prior is None else (trxr_prior, trxr_prior_sigma)
    )
    diag.config["failed_candidates"] = {}
    bp_null, _ = fit_cable_reflection(
        obs.freqs, current.G, current.sigma_G, smooth_order=smooth_order
    )
    diag.initial_gap = gap_metrics(current, obs, tpl, bp_null)
    diag.residual_snapshots.append(("initial model", current.residuals_of(0, 0)))
    # a large observation: each step fits in full only the candidates whose score says
    # they could win (_StepScreen)
    large = is_large(obs.shape)
    plan: _StepScreen | None = None

    def try_candidates(step: int) -> tuple[list[tuple[Any, ...]], ExtendedFit | None]:
        """Fit every candidate not yet in the model.

        Returns the accepted candidates' ``(nan, dchi2, k, effect, fit, c)`` and the
        lowest-chi2 model fitted (rejected candidates included: see
        :func:`_escape_local_minimum`).
        """
        results: list[tuple[Any, ...]] = []
        lowest: ExtendedFit | None = None
        for icand, eff in enumerate(cands if plan is None else plan.order):
            progress(
                (step + icand / len(cands)) / max_steps,
                f"step {step + 1}: trying {eff.name} ({eff.basis}, order {eff.order})",
            )
            if any(a.name == eff.name for a in active) or (
                eff.kind == "bandpass" and cable is not None
            ):
                continue
            if plan is not None and plan.skip(eff, results):
                continue
            if eff.kind == "bandpass":
                null, rip = fit_cable_reflection(
                    obs.freqs, current.G, current.sigma_G, smooth_order=smooth_order
                )
                if rip.at_edge:
                    diag.config["failed_candidates"]["cable_reflection"] = (
                        f"best delay {rip.tau_ns:.0f} ns at the edge of the searched range: "
                        "unresolved bandpass structure, not a reflection"
                    )
                    continue
                dchi = null.chi2 - rip.chi2
                k = rip.nparam - null.nparam
                chat = max(1.0, rip.reduced_chi2)
                stat = dchi / chat - k * math.log(max(null.nfreq, 2))
                results.append((stat, dchi, k, eff, rip, chat))
                continue
            if eff.kind == "feed_gain":
                if eff.name in feed_accepted:
                    continue  # held in the data already
                # a per-antenna jitter is tested once a common series is in the model
                # (nested: it replaces it); a per-antenna drift unless every antenna-pol
                # has its own series already (which holds any drift of its own)
                if eff.basis == "feed_integration":
                    if not any(a.basis == "integration" for a in active):
                        continue
                elif "antenna_gain_jitter" in feed_accepted:
                    continue
                if obs.nant * len(obs.pols) > FEED_JITTER_MAX_FEEDS:
                    diag.config["failed_candidates"][eff.name] = (
                        f"not tested: {obs.nant * len(obs.pols)} antenna-pols (at most "
                        f"{FEED_JITTER_MAX_FEEDS}, one fit each; select fewer antennas)"
                    )
                    continue
                try:
                    feed = fit_feed_gains(obs, tpl, active, current, w, prior_kw, eff)
                except DiagnoseError as exc:
                    diag.config["failed_candidates"][eff.name] = f"not tested: {exc}"
                    continue
                rough = (
                    feed_departures_rough(feed, current, obs, tpl)
                    if feed is not None and eff.basis == "feed_integration"
                    else None
                )
                if rough is not None and rough <= bic_threshold:
                    diag.config["failed_candidates"][eff.name] = (
                        "the antenna-pols' departures from the common series are smooth "
                        "functions of time (Legendre order "
                        f"{JITTER_SMOOTH_ORDER} and the sky's time shapes) up to a remainder "
                        f"that does not pay for its parameters (Delta BIC {rough:.3g}): a "
                        "smooth per-antenna change, not jitter"
                    )
                    continue
                if feed is not None:
                    results.append(
                        (math.nan, feed.delta_chi2, feed.k, eff, feed, feed.reduced_chi2)
                    )
                continue
            if eff.kind == "gain" and any(
                a.kind == "gain" and a.basis == "integration" for a in active
            ):
                continue  # nested: a per-integration gain already absorbs any gain drift
            try:
                # from the current model's values (a new effect starts at zero): a model
                # of several effects is not linear in them, and from zero Gauss-Newton
                # can stop in a local minimum
                trial = fit_extended(
                    obs, tpl, [*active, eff], weights=w, start=current.params, **prior_kw
                )
            except (DiagnoseError, np.linalg.LinAlgError) as exc:
                label = f"{eff.name}/{eff.basis}{eff.order}"
                logger.warning("candidate %s failed: %s", label, exc)
                diag.config["failed_candidates"][label] = str(exc)
                continue
            if lowest is None or trial.chi2 < lowest.chi2:
                lowest = trial
            if eff.name not in diag.identifiability:
                diag.identifiability[eff.name] = trial.identifiable.get(eff.name, 0.0)
            if trial.identifiable.get(eff.name, 0.0) < MIN_IDENTIFIABLE:
                continue
            limit = PLAUSIBLE_LIMITS.get(eff.name)
            values = np.abs(np.asarray(trial.params.get(eff.name, []), float))
            if limit is not None and eff.fixed is None and np.any(values > limit):
                diag.config["failed_candidates"][f"{eff.name}/{eff.basis}{eff.order}"] = (
                    f"best fit {np.round(trial.params[eff.name], 4).tolist()} beyond the "
                    f"plausible range (|value| <= {limit:g}): the template absorbs other "
                    "structure"
                )
                continue
            if eff.name == "timing_offset" and abs(trial.params[eff.name][0]) > TIMING_MAX_S:
                diag.config["failed_candidates"]["timing_offset"] = (
                    f"best dt {trial.params[eff.name][0]:.0f} s is beyond the linear "
                    f"template's range (+-{TIMING_MAX_S:.0f} s; a frame error of decades is "
                    "~1 min): the template absorbs other time structure, not a timing error"
                )
                continue
            if eff.basis == "integration":
                eps = np.concatenate([[0.0], trial.params[eff.name]])
                sig = np.concatenate([[0.0], trial.sigmas[eff.name]])
                white, info = jitter_is_significant(
                    eps,
                    sig,
                    obs.lsts,
                    sky_time_shapes(tpl),
                    ndata=trial.ndata,
                    overdispersion=robust_overdispersion(trial),
                )
                diag.config.setdefault("jitter_tests", []).append({"step": step + 1, **info})
                if not white:
                    diag.config["failed_candidates"]["gain_jitter"] = (
                        "its per-integration series is a smooth function of time (Legendre "
                        f"order {JITTER_SMOOTH_ORDER}) and of the sky's own time shape up to "
                        f"a remainder that does not pay for its parameters (Delta BIC "
                        f"{info['rough_delta_bic']:.3g}; {100 * info['smooth_fraction']:.0f} % "
                        "of the power smooth): a smooth effect or a sky-model error, not jitter"
                    )
                    continue
            # a candidate that would pass on its Delta chi2 must pass on its own parameters
            wald = wald_statistic(trial, eff)
            penalty = eff.nfree * math.log(current.ndata)
            chat_own = max(1.0, trial.reduced_chi2)
            dchi_own = current.chi2 - trial.chi2
            if (
                wald is not None
                and dchi_own / chat_own - penalty > bic_threshold
                and wald / chat_own - penalty <= bic_threshold
                # the diagonal Wald of correlated parameters (a diurnal sine and cosine)
                # falls short of Delta chi2 a little even for a linear model: only a
                # large shortfall is the other parameters moving
                and wald < WALD_SHORTFALL * dchi_own
            ):
                label = f"{eff.name}/{eff.basis}{eff.order}"
                diag.config["failed_candidates"][label] = (
                    f"its own parameters are consistent with zero (Wald chi2 {wald:.3g} for "
                    f"{eff.nfree}) though the fit improves by Delta chi2 "
                    f"{current.chi2 - trial.chi2:.3g}: the other parameters moved along a "
                    "nearly degenerate valley, not evidence for this effect"
                )
                continue
            k, stat_fit = eff.nfree, trial
            if eff.name == "missing_cmb":
                # a discrete hypothesis, m = +-1, nested in sky_offset (T_offset = -+2.725 K):
                # no free parameter, so that it wins over sky_offset when it fits as well
                m = 1.0 if trial.params[eff.name][0] > 0 else -1.0
                # ... but only if the data ask for a CMB-shaped offset at all: the free
                # factor must pay for its parameter (else a small offset of any origin,
                # e.g. a horizon treated differently, passes for a missing CMB)
                free_stat = (current.chi2 - trial.chi2) / max(1.0, trial.reduced_chi2) - math.log(
                    current.ndata
                )
                if free_stat <= bic_threshold:
                    diag.config["failed_candidates"]["missing_cmb"] = (
                        f"the free CMB factor {trial.params[eff.name][0]:.3g} +- "
                        f"{trial.sigmas[eff.name][0]:.2g} does not pay for its parameter "
                        f"(Delta BIC {free_stat:.3g})"
                    )
                    continue
                fixed_eff = Effect(**{**eff.__dict__, "fixed": (m,)})
                stat_fit = fit_extended(
                    obs, tpl, [*active, fixed_eff], weights=w, start=trial.params, **prior_kw
                )
                k = 0
                stat_fit = (stat_fit, trial, fixed_eff)  # type: ignore[assignment]
            fit_for_chi = stat_fit[0] if isinstance(stat_fit, tuple) else stat_fit
            dchi = current.chi2 - fit_for_chi.chi2
            results.append((math.nan, dchi, k, eff, stat_fit, fit_for_chi.reduced_chi2))
        return results, lowest

    restarts = 0
    consistency: dict[str, dict[str, Any]] = {}
    feed_accepted: set[str] = set()
    for step in range(max_steps):
        while True:
            plan = (
                _StepScreen(obs, tpl, active, current, cands, w, prior_kw, diag) if large else None
            )
            results, lowest = try_candidates(step)
            escaped = (
                _escape_local_minimum(obs, tpl, active, current, lowest, w, prior_kw, bic_threshold)
                if restarts < MAX_RESTARTS and lowest is not None
                else None
            )
            if escaped is None:
                break
            restarts += 1
            diag.config.setdefault("restarts", []).append(
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
            w = radiometer_weights(obs, escaped)
            current = fit_extended(obs, tpl, active, weights=w, start=escaped.params, **prior_kw)
        if plan is not None:
            diag.config.setdefault("screening", []).append({"step": step + 1, **plan.report()})
        if results:
            # one overdispersion for every time-domain candidate of a step (as in QAIC,
            # from the best-fitting model), so that tiny differences of chi2/dof between
            # candidates are not multiplied by a huge Delta chi2
            own = [r[5] for r in results if r[3].kind != "bandpass"]
            chat_t = max(1.0, min(own)) if own else 1.0
            results = [
                r
                if r[3].kind == "bandpass"
                else (
                    r[1] / chat_t - r[2] * math.log(current.ndata),
                    r[1],
                    r[2],
                    r[3],
                    r[4],
                    chat_t,
                )
                for r in results
            ]
            # best variant of each effect name first, then best overall
            results.sort(key=lambda r: -r[0])
        if not results:
            break
        candidates_report = {}
        for r in results:
            candidates_report.setdefault(r[3].name, float(r[0]))
        # the best candidate whose parameters the two halves of the band agree on: an
        # effect of the catalogue is the same at every frequency, a template absorbing
        # structure of another origin (a beam-shape error, say) is not
        best = results[0]
        for r in results:
            r_stat, r_dchi, r_k, r_eff, r_payload, r_chat = r
            r_p = float(stats.chi2.sf(r_dchi / r_chat, max(r_k, 1)))
            if not (r_stat > bic_threshold and r_p < alpha):
                break
            best = r
            if r_eff.kind in ("bandpass", "feed_gain"):
                break
            free_fit = r_payload[1] if isinstance(r_payload, tuple) else r_payload
            check = band_consistency(obs, tpl, active, r_eff, free_fit, w, prior_kw)
            if check is not None and not check["consistent"]:
                check = _consistent_with_partner(
                    obs, tpl, active, r, results, w, prior_kw, bic_threshold, alpha, check
                )
            if check is None or check["consistent"]:
                if check is not None:
                    consistency[r_eff.name] = check
                break
            label = f"{r_eff.name}/{r_eff.basis}{r_eff.order}"
            diag.config["failed_candidates"][label] = (
                f"Delta BIC {r_stat:.3g}, but the two halves of the band disagree on its "
                f"parameters ({check['message']}): its template absorbs structure of "
                "another origin"
            )
            logger.info("step %d: %s inconsistent across the band", step + 1, r_eff.name)
            best = None
        if best is None:
            diag.config["last_rejected"] = {
                "name": results[0][3].name,
                "statistic": float(results[0][0]),
                "p_value": float(
                    stats.chi2.sf(results[0][1] / results[0][5], max(results[0][2], 1))
                ),
                "reason": "significant, but the two halves of the band disagree on it "
                "and on every other significant candidate (failed_candidates)",
                "candidates": candidates_report,
            }
            break
        stat, dchi, k, eff, payload, chat = best
        pval = float(stats.chi2.sf(dchi / chat, max(k, 1)))
        logger.info("step %d: best %s (Delta BIC %.1f, p %.2g)", step + 1, eff.name, stat, pval)
        if not (stat > bic_threshold and pval < alpha):
            diag.config["last_rejected"] = {
                "name": eff.name,
                "statistic": stat,
                "p_value": pval,
                "candidates": candidates_report,
            }
            break
        gap_before = gap_metrics(current, obs, tpl, bp_null)
        step_extra: dict[str, Any] = {}
        if eff.kind == "bandpass":
            rip: BandpassFit = payload
            cable = (rip, eff)
            params = {
                "a": {"value": rip.a, "sigma": rip.sigma_a},
                "tau_ns": {"value": rip.tau_ns, "sigma": rip.sigma_tau_ns},
                "phi": {"value": rip.phi, "sigma": rip.sigma_phi},
            }
            feeds = [(a, p) for a in obs.antennas for p in obs.pols]
            step_extra["per_feed"] = [
                {"antenna": int(a), "pol": str(p), **vals}
                for (a, p), vals in zip(feeds, rip.per_feed, strict=True)
            ]
            step_extra["smooth_bandpass_order"] = rip.smooth_order
            step_extra["masked_channels"] = rip.masked_channels
            gap_after = dict(gap_before)
            gap_after["bandpass_reduced_chi2"] = rip.reduced_chi2
            bp_null = rip
            diag.residual_snapshots.append((f"after {eff.name}", current.residuals_of(0, 0)))
        elif eff.kind == "feed_gain":
            feed: FeedGainFit = payload
            feed_accepted.add(eff.name)
            # every antenna-pol's own series: its departure from what the antenna-pols
            # share (the common jitter series, or their mean drift) is divided out of the
            # data and held at its estimate from here on; the shared part stays with the
            # model, free, so that later candidates are fitted jointly with it (held
            # whole, a jitter series would keep whatever trend it absorbed, e.g. most of
            # a noise drift)
            jitter = eff.basis == "feed_integration"
            if jitter:
                shared = current.gain_factor / np.mean(current.gain_factor)
            else:
                shared = feed.factors.mean(axis=(0, 1))
            obs = dataclasses.replace(obs, data=obs.data / (feed.factors / shared)[..., None])
            new = fit_extended(obs, tpl, active, weights=w, start=current.params, **prior_kw)
            impact = product_impact(current, new, sigma_g, sigma_t)
            diff = feed.factors - (shared if jitter else 1.0)
            impact["G_time"] = {
                "rms_relative_change": float(np.sqrt(np.mean(diff**2))),
                "max_abs_relative_change": float(np.max(np.abs(diff))),
            }
            step_extra["product_impact"] = impact
            step_extra["negligible"] = is_negligible(impact, dchi / current.ndata)
            gap_after = gap_metrics(new, obs, tpl, bp_null)
            w = radiometer_weights(obs, new)
            current = fit_extended(obs, tpl, active, weights=w, start=new.params, **prior_kw)
            diag.residual_snapshots.append((f"after {eff.name}", current.residuals_of(0, 0)))
            rms = np.std(feed.factors, axis=-1)
            swing = np.ptp(feed.factors, axis=-1)
            params = {
                "rms": {"value": float(np.median(rms)), "sigma": float(np.median(feed.sigmas))},
                "max_rms": {"value": float(np.max(rms)), "sigma": float(np.max(feed.sigmas))},
            }
            if not jitter:
                params["max_change"] = {"value": float(np.max(swing)), "sigma": 0.0}
            step_extra["per_feed"] = []
            for ia, a in enumerate(obs.antennas):
                for ip, p in enumerate(obs.pols):
                    row = {"antenna": int(a), "pol": str(p), "rms": float(rms[ia, ip])}
                    if not jitter and feed.values is not None:
                        own = zip(eff.params, feed.values[ia, ip], strict=True)
                        row.update({name: float(v) for name, v in own})
                    step_extra["per_feed"].append(row)
            step_extra["series"] = {
                "lst_h": obs.lsts.tolist(),
                "gain_factor": feed.factors.tolist(),
                "shared_gain_factor": np.broadcast_to(shared, (obs.ntime,)).tolist(),
            }
        else:
            if isinstance(payload, tuple):
                _, free_fit, fixed_eff = payload
                params = _params_dict(eff, free_fit)
                params["cmb_factor"]["adopted"] = float(fixed_eff.fixed[0])
                active.append(fixed_eff)
            else:
                params = _params_dict(eff, payload)
                active.append(eff)
            start = (payload[0] if isinstance(payload, tuple) else payload).params
            new = fit_extended(obs, tpl, active, weights=w, start=start, **prior_kw)
            impact = product_impact(current, new, sigma_g, sigma_t)
            gap_after = gap_metrics(new, obs, tpl, bp_null)
            step_extra["product_impact"] = impact
            # detected, but it moves G and Trxr by a small fraction of their total errors:
            # kept in the fitted model (else other entries would absorb what it explains)
            # and reported as negligible, not named among the effects
            step_extra["negligible"] = is_negligible(impact, dchi / current.ndata)
            # re-weight with the improved model for the next step
            w = radiometer_weights(obs, new)
            current = fit_extended(obs, tpl, active, weights=w, start=new.params, **prior_kw)
            # the effects accepted before are re-tested against the refit: one that the
            # new effect explains away is dropped now, before the search goes on
            active, current = _retest_accepted(
                obs,
                tpl,
                active,
                current,
                w,
                prior_kw,
                bic_threshold,
                diag,
                f"step {step + 1}",
                keep=active[-1],
            )
            diag.residual_snapshots.append((f"after {eff.name}", current.residuals_of(0, 0)))
            if not isinstance(payload, tuple):
                params = _params_dict(eff, current)
            if eff.basis == "integration":
                eps = np.concatenate([[0.0], current.params[eff.name]])
                step_extra["series"] = {
                    "lst_h": obs.lsts.tolist(),
                    "gain_factor": ((1 + eps) / np.mean(1 + eps)).tolist(),
                    "sigma": np.concatenate([[0.0], current.sigmas[eff.name]]).tolist(),
                }
        if eff.name in consistency:
            step_extra["band_consistency"] = consistency.pop(eff.name)
        if eff.order:
            if eff.basis not in ("integration", "feed_integration"):
                params["order"] = {"value": float(eff.order), "sigma": 0.0}
            step_extra["time_basis"] = eff.basis
        diag.steps.append(
            {
                "name": eff.name,
                "parameters": params,
                "statistic": float(stat),
                "delta": float(dchi),
                "k": int(k),
                "p_value": pval,
                "gap_before": gap_before,
                "gap_after": gap_after,
                "overdispersion": float(chat),
                "candidates": candidates_report,
                **step_extra,
            }
        )
        if step_extra.get("negligible"):
            diag.negligible.append(eff.name)
            logger.info("step %d: %s detected, negligible for the products", step + 1, eff.name)
        else:
            diag.effects.append(eff.name)
        _supersede(diag, feed_accepted)
    # final backward pass (also run after every accepted step, below)
    active, current = _retest_accepted(
        obs, tpl, active, current, w, prior_kw, bic_threshold, diag, "the final model"
    )
    diag.final_gap = gap_metrics(current, obs, tpl, bp_null)
    diag.final_fit = current
    diag.unexplained = describe_unexplained(current, obs, diag.final_gap)
    diag.product_change = product_impact(base_fit, current, sigma_g, sigma_t)
    diag.product_change["note"] = (
        "G and Trxr of the starting model against the diagnosed model (time-domain effects; "
        "a cable reflection is a bandpass feature, its G is unchanged); changes in units of "
        "the total 1-sigma of the ordinary calibration"
    )
    # every accepted effect's parameters from the final joint fit (a step's parameters
    # are those of the model at that step, before later effects were added)
    for st in diag.steps:
        if "dropped_in_backward_pass" in st:
            continue
        if st["name"] == "cable_reflection" or st["name"] not in current.params:
            final = dict(st["parameters"])
        else:
            eff = next(e for e in active if e.name == st["name"])
            final = _params_dict(eff, current) if eff.fixed is None else dict(st["parameters"])
            if "order" in st["parameters"]:
                final["order"] = st["parameters"]["order"]
        diag.final_parameters[st["name"]] = final
    return diag


# output ---------------------------------------------------------------------------------


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def summary_text(diag: Diagnosis) -> str:
    """Human-readable summary of a diagnosis."""
    g0 = diag.initial_gap
    lines = [
        "autocal diagnose",
        f"statistic: {diag.config.get('statistic')}",
        f"threshold: Delta BIC > {diag.config.get('bic_threshold')} and "
        f"p < {diag.config.get('alpha')}",
        f"initial gap: chi2/dof = {g0.get('reduced_chi2', float('nan')):.4f}, "
        f"rms residual = {g0.get('rms_normalised_residual', float('nan')):.3f}",
        "",
    ]
    if not diag.steps and not diag.unexplained:
        lines.append("no significant effect found: the model is consistent with the data")
    elif not diag.steps:
        lines.append("no catalogue entry explains the gap (see 'unexplained' below)")
    for i, st in enumerate(diag.steps, 1):
        pars = ", ".join(
            f"{k} = {v['value']:.5g} +- {v['sigma']:.2g}" for k, v in st["parameters"].items()
        )
        marks = " [negligible]" if st.get("negligible") else ""
        if st.get("superseded_by"):
            marks += f" [superseded by {st['superseded_by']}]"
        if st.get("dropped_in_backward_pass"):
            marks += f" [dropped at {st['dropped_in_backward_pass'].get('at', 'a re-test')}]"
        lines.append(
            f"step {i}: {st['name']}{marks} ({pars}); "
            f"Delta BIC = {st['statistic']:.1f}, "
            f"Delta chi2 = {st['delta']:.1f}; chi2/dof {st['gap_before']['reduced_chi2']:.4f} "
            f"-> {st['gap_after']['reduced_chi2']:.4f}"
        )
        if st.get("product_impact"):
            lines.append("  " + _impact_text(st["product_impact"]))
    if diag.negligible:
        lines.append(
            "detected, negligible for the calibration products (kept in the fit, not named): "
            + ", ".join(diag.negligible)
        )
    rej = diag.config.get("last_rejected")
    if rej:
        lines.append(
            f"best remaining candidate {rej['name']}: Delta BIC = {rej['statistic']:.1f} "
            f"({rej.get('reason') or 'not significant'})"
        )
    lines.append("")
    lines.append("not identifiable from these data (Fisher fraction after (G, n) projection):")
    for name, frac in sorted(diag.identifiability.items()):
        if frac < MIN_IDENTIFIABLE:
            shown = f"{frac:.2e}" if frac > 0 else f"< {IDENTIFIABLE_RESOLUTION:.0e} (degenerate)"
            lines.append(f"  {name}: {shown}")
    fg = diag.final_gap
    lines.append(
        f"final gap: chi2/dof = {fg.get('reduced_chi2', float('nan')):.4f}, "
        f"rms residual = {fg.get('rms_normalised_residual', float('nan')):.3f}"
    )
    if diag.unexplained:
        lines.append(diag.unexplained["message"])
    if diag.steps and diag.product_change:
        lines.append("calibration products, starting model -> diagnosed model: ")
        lines.append("  " + _impact_text(diag.product_change))
    return "\n".join(lines) + "\n"


def _impact_text(impact: dict[str, Any]) -> str:
    """One line on how G and Trxr moved (see :func:`product_impact`)."""
    g, t = impact.get("G", {}), impact.get("Trxr", {})
    nan = float("nan")
    if "median_change_over_sigma" not in g:
        return "no channel to compare"
    verdict = "significant" if impact.get("significant") else "within the errors"
    return (
        f"G changes by {100 * g['median_relative_change']:+.2g} % (median; "
        f"{g['median_change_over_sigma']:.2g} total sigma, worst channel "
        f"{g['max_change_over_sigma']:.2g}); Trxr by {t.get('median_change_K', nan):+.3g} K "
        f"({t.get('median_change_over_sigma', nan):.2g} sigma, worst "
        f"{t.get('max_change_over_sigma', nan):.2g}): {verdict}" + _time_change_text(impact)
    )


def _time_change_text(impact: dict[str, Any]) -> str:
    """How the products' variation in time changed, when it did (see :func:`is_negligible`)."""
    gt, tt = impact.get("G_time", {}), impact.get("Trxr_time", {})
    parts = []
    if gt.get("max_abs_relative_change", 0.0) >= NEGLIGIBLE_G_FRACTION:
        parts.append(
            f"G(t) {100 * gt['rms_relative_change']:.2g} % rms over time (largest "
            f"{100 * gt['max_abs_relative_change']:.2g} %)"
        )
    if tt.get("max_abs_change_K", 0.0) >= NEGLIGIBLE_TRXR_K:
        parts.append(
            f"Trxr(t) up to {tt['median_max_abs_change_K']:.3g} K (median channel; largest "
            f"{tt['max_abs_change_K']:.3g} K)"
        )
    return f"; in time: {', '.join(parts)}" if parts else ""


def write_diagnosis(diag: Diagnosis, out_dir: str | Path, obs: Observation | None = None) -> Path:
    """Write ``diagnosis.json``, ``summary.txt`` and plots.

    The plots: residual waterfalls before/after each step, and ``gain_series.png`` (the
    per-integration gain series of ``gain_jitter`` / ``antenna_gain_jitter`` steps).

    Parameters
    ----------
    diag
        The diagnosis.
    out_dir
        Output folder (created).
    obs
        The observation (axes of the residual plots); without it the plots use indices.

    Returns
    -------
    Path
        The folder.
    """
    from autocal.plots import plot_gain_series, plot_residuals

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "diagnosis.json").write_text(json.dumps(_jsonable(diag.to_dict()), indent=2))
    (out / "summary.txt").write_text(summary_text(diag))
    snaps = diag.residual_snapshots
    for i in range(1, len(snaps)):
        before, after = snaps[i - 1], snaps[i]
        nt, nf = after[1].shape
        freqs = obs.freqs if obs is not None else np.arange(nf) * 1e6
        lsts = obs.lsts if obs is not None else np.arange(nt, dtype=float)
        plot_residuals(
            [before[0], after[0]],
            np.stack([before[1], after[1]]),
            freqs,
            lsts,
            out / f"residuals_step{i}.png",
        )
    if len(snaps) == 1 and obs is not None:
        plot_residuals([snaps[0][0]], snaps[0][1][None], obs.freqs, obs.lsts, out / "residuals.png")
    plot_gain_series(diag.steps, out / "gain_series.png")
    logger.info("wrote diagnosis to %s", out)
    return out
