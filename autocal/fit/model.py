"""The fit's time model, its design and its weights.

Per antenna, polarisation and channel the data are ``R(t) = G(t) Tsky(t) + n(t)`` with

- the *constant* model: ``G(t) = G``, ``n(t) = n`` (parameters ``x = (G, n)``);
- the *Legendre* model of order ``p``: ``G(t) = sum_k g_k P_k(s)``, ``n(t) = sum_k n_k
  P_k(s)``, ``s`` the LST mapped linearly onto ``[-1, 1]`` over the model's LST range
  (``x = (g_0..g_p, n_0..n_p)``; order 1 is the paper's ``G0 + G1 t``).

:class:`FitModel` is the model, :func:`design` its design features and :func:`mean_vectors`
the vectors that give the time-averaged ``(G, n)`` from its parameters.

Weights ``W`` (:func:`weights_for`):

- ``"radiometer"``: ``sigma = R / sqrt(dnu dt N)`` (radiometer equation; ``dnu`` channel
  width, ``dt`` integration time, ``N`` the sample count). The first pass uses the data
  for ``R``; later passes (``iterations``) use the fitted model, which removes the small
  bias that data-derived weights carry (``-2 sigma_R^2 / R^2`` relative, see the tests).
- ``"identity"``: unit weights (what the paper used on real data). The covariance is then
  scaled by ``chi^2 / dof`` (the residual variance), the usual OLS estimate.
- an array of inverse variances ``1 / sigma^2`` broadcastable to the data.

Flagged and non-finite samples get zero weight and are counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.polynomial import legendre

from autocal.errors import AutocalError


class FitError(AutocalError):
    """Invalid fit input."""


def unwrap_lsts(lsts: np.ndarray) -> np.ndarray:
    """Return LSTs (hours, in time order) made continuous across the 24 h wrap."""
    lsts = np.asarray(lsts, dtype=np.float64)
    return np.unwrap(lsts * (2 * np.pi / 24.0)) * (24.0 / (2 * np.pi))


@dataclass(frozen=True)
class FitModel:
    """Which model to fit.

    Parameters
    ----------
    kind
        ``"constant"`` or ``"legendre"``.
    order
        Legendre order ``p`` (0 for the constant model).
    lst_start, lst_span
        The LST (hours) mapped to ``s = -1`` and the span (hours) mapped to ``s = 2``;
        set from the data by :meth:`for_lsts`. Unused by the constant model.
    """

    kind: Literal["constant", "legendre"] = "constant"
    order: int = 0
    lst_start: float = 0.0
    lst_span: float = 24.0

    def __post_init__(self) -> None:
        if self.kind not in ("constant", "legendre"):
            raise FitError(f"unknown model {self.kind!r}: use 'constant' or 'legendre'")
        if self.kind == "constant" and self.order != 0:
            raise FitError("the constant model has order 0; use kind='legendre' for order > 0")
        if not 0 <= self.order <= 20:
            raise FitError(f"Legendre order must be in 0..20, got {self.order}")
        if not (np.isfinite(self.lst_span) and self.lst_span > 0):
            raise FitError("the model's LST span must be positive")

    @classmethod
    def for_lsts(cls, lsts: np.ndarray, kind: str = "constant", order: int = 0) -> FitModel:
        """Build a model whose time axis spans the given LSTs (hours, time order)."""
        un = unwrap_lsts(lsts)
        span = float(un.max() - un.min())
        if kind == "legendre" and order > 0 and span <= 0:
            raise FitError("a time-dependent model needs data at more than one LST")
        return cls(kind, order, float(un.min() % 24.0), span if span > 0 else 24.0)  # type: ignore[arg-type]

    @property
    def nbasis(self) -> int:
        """Number of time basis functions ``p + 1``."""
        return self.order + 1

    @property
    def nparam(self) -> int:
        """Number of parameters per channel ``2 (p + 1)``."""
        return 2 * self.nbasis

    @property
    def param_names(self) -> tuple[str, ...]:
        """``("G", "n")`` or ``("g_0", .., "g_p", "n_0", .., "n_p")``."""
        if self.kind == "constant":
            return ("G", "n")
        k = range(self.nbasis)
        return tuple(f"g_{i}" for i in k) + tuple(f"n_{i}" for i in k)

    def s(self, lsts: np.ndarray) -> np.ndarray:
        """Map LSTs (hours) onto the model's ``[-1, 1]`` coordinate."""
        offset = (np.asarray(lsts, dtype=np.float64) - self.lst_start) % 24.0
        # An LST outside a span shorter than a day is put on the nearer side of it
        # (before the start: s < -1; after the end: s > 1).
        if self.lst_span < 24.0:
            offset = np.where(
                offset > self.lst_span + (24.0 - self.lst_span) / 2, offset - 24, offset
            )
        return 2.0 * offset / self.lst_span - 1.0

    def basis(self, lsts: np.ndarray) -> np.ndarray:
        """Return ``(nbasis, Ntime)`` Legendre polynomials ``P_k(s(t))``."""
        if self.kind == "constant":
            return np.ones((1, np.size(lsts)))
        return legendre.legvander(self.s(lsts), self.order).T

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description."""
        return {
            "kind": self.kind,
            "order": self.order,
            "lst_start_h": self.lst_start,
            "lst_span_h": self.lst_span,
            "parameters": list(self.param_names),
        }


def design(model: FitModel, tsky: np.ndarray, lsts: np.ndarray) -> np.ndarray:
    """Return the design features ``(Npol, Nfreq, Ntime, nparam)``.

    Parameters
    ----------
    model
        The fit model.
    tsky
        ``(Npol, Ntime, Nfreq)`` (or ``(Ntime, Nfreq)``) model sky temperature in kelvin.
    lsts
        ``(Ntime,)`` hours.
    """
    tsky = np.asarray(tsky, dtype=np.float64)
    if tsky.ndim == 2:
        tsky = tsky[None]
    basis = model.basis(lsts)  # (K, T)
    tt = np.swapaxes(tsky, 1, 2)  # (P, F, T)
    gain_part = tt[..., None] * basis.T[None, None]  # (P, F, T, K)
    noise_part = np.broadcast_to(basis.T[None, None], gain_part.shape)
    return np.concatenate([gain_part, noise_part], axis=-1)


def check_tsky(tsky: np.ndarray, npol: int, ntime: int, nfreq: int) -> np.ndarray:
    """Return ``tsky`` as a finite float64 ``(Npol, Ntime, Nfreq)`` array.

    A ``(Ntime, Nfreq)`` array applies to every polarisation (a broadcast view). A wrong
    shape or a non-finite value raises :class:`FitError`.
    """
    tsky = np.asarray(tsky, dtype=np.float64)
    if tsky.ndim == 2:
        tsky = np.broadcast_to(tsky[None], (npol, *tsky.shape))
    if tsky.shape != (npol, ntime, nfreq):
        raise FitError(
            f"Tsky has shape {tsky.shape}; expected (Npol, Ntime, Nfreq) = "
            f"{(npol, ntime, nfreq)} or (Ntime, Nfreq)"
        )
    if not np.all(np.isfinite(tsky)):
        raise FitError("the Tsky model has non-finite values")
    return tsky


def weights_for(
    weights: str | np.ndarray,
    data: np.ndarray,
    usable: np.ndarray,
    bandwidth_time: np.ndarray | float | None,
    reference: np.ndarray | None = None,
) -> np.ndarray:
    """Return inverse-variance weights (zero where not usable).

    Parameters
    ----------
    weights
        ``"radiometer"``, ``"identity"`` or an array of ``1 / sigma^2``.
    data
        ``(Nant, Npol, Ntime, Nfreq)`` auto-correlations.
    usable
        Boolean mask of samples to use.
    bandwidth_time
        ``dnu dt N`` per sample (radiometer weights only).
    reference
        Power used in the radiometer equation instead of the data (e.g. a model).
    """
    if isinstance(weights, str):
        if weights == "identity":
            return usable.astype(np.float64)
        if weights == "radiometer":
            if bandwidth_time is None:
                raise FitError("radiometer weights need the channel width and integration time")
            power = data if reference is None else reference
            bt = np.broadcast_to(np.asarray(bandwidth_time, np.float64), data.shape)
            with np.errstate(divide="ignore", invalid="ignore"):
                w = bt / power**2
            ok = usable & np.isfinite(w) & (w > 0)
            return np.where(ok, w, 0.0)
        raise FitError(
            f"unknown weights {weights!r}: use 'radiometer', 'identity' or an array of 1/sigma^2"
        )
    w = np.broadcast_to(np.asarray(weights, np.float64), data.shape)
    if np.any(w[usable] < 0) or not np.all(np.isfinite(w[usable])):
        raise FitError("user weights (1/sigma^2) must be finite and >= 0")
    return np.where(usable, w, 0.0)


def mean_vectors(model: FitModel, lsts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the vectors ``(vg, vn)`` that give the time-averaged ``G`` and ``n``.

    ``G = vg . x`` and ``n = vn . x`` for the parameters ``x`` of ``model``, averaged over
    the integrations at ``lsts``.
    """
    tavg = model.basis(lsts).mean(axis=1)
    nb = model.nbasis
    vg = np.zeros(model.nparam)
    vn = np.zeros(model.nparam)
    vg[:nb] = tavg
    vn[nb:] = tavg
    return vg, vn
