"""The Tsky records: a table (:class:`TskyResult`), LST harmonics (:class:`TskyHarmonics`).

:class:`TskyResult` is Tsky(nu, LST) on given grids; :class:`TskyHarmonics` is the ring-FFT
engine's LST-free output (Tsky's Fourier series in LST and the beam integrals), what the
Tsky cache stores (:mod:`autocal.tsky.cache`, files by :mod:`autocal.io.tskyfile`) and
turns into a table for any LSTs and ground temperature. Also the checks of the grids and
of the ground temperature every Tsky computation shares, and :class:`TskyError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from autocal.core.reprs import median, span
from autocal.errors import AutocalError
from autocal.tsky.synthesis import lst_radians, synthesise

#: Default ground temperature in kelvin.
T_GROUND = 300.0


class TskyError(AutocalError):
    """Invalid input to the Tsky computation."""


@dataclass(frozen=True)
class TskyResult:
    """A Tsky table.

    Attributes
    ----------
    tsky
        ``(Nlst, Nfreq)`` beam-weighted sky temperature in kelvin (CMB and ground included).
    freqs
        ``(Nfreq,)`` Hz.
    lsts
        ``(Nlst,)`` local sidereal times in hours.
    f_above, f_below
        ``(Nfreq,)`` fractions of the beam integral above / below the horizon.
    meta
        Description of the sky, beam, site, ground temperature, resolution, epoch, method.
    components
        Optional ``(Nlst, Nfreq, Ncomp)`` contribution of each sky component's *spatial
        map* (unit spectrum) to Tsky; ``tsky = sum_c spectra[f, c] components[..., c] +
        Tgnd f_below``. Lets a caller change component spectra without recomputing.
    spectra
        ``(Nfreq, Ncomp)`` the sky's component spectra, when ``components`` is given.
    """

    tsky: np.ndarray
    freqs: np.ndarray
    lsts: np.ndarray
    f_above: np.ndarray
    f_below: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    components: np.ndarray | None = None
    spectra: np.ndarray | None = None

    def __repr__(self) -> str:
        """Return one line: sky, beam, site, grid and Tsky's range (never the arrays)."""
        sky = (self.meta.get("sky") or {}).get("model", "?")
        beam_meta = self.meta.get("beam") or {}
        beam = f"{beam_meta.get('beam', '?')} {beam_meta.get('pol', '')}".rstrip()
        site = (self.meta.get("site") or {}).get("name", "?")
        tsky = np.asarray(self.tsky)
        finite = tsky[np.isfinite(tsky)]
        trange = f"{finite.min():.4g}-{finite.max():.4g} K" if finite.size else "-"
        comps = "" if self.components is None else f", {self.components.shape[-1]} components"
        return (
            f"TskyResult(sky {sky}, beam {beam}, site {site}: {self.lsts.size} LSTs "
            f"{span(self.lsts, 1, 'h')} x {self.freqs.size} channels "
            f"{span(self.freqs, 1e6, 'MHz')}; Tsky {trange}, median {median(tsky):.4g} K, "
            f"median f_below {median(self.f_below):.3g}{comps})"
        )


@dataclass(frozen=True)
class TskyHarmonics:
    """Tsky at every LST at once: its Fourier series in LST (the engine's LST-free output).

    For a drift scan the beam-weighted sky is periodic in LST, band-limited at
    ``m <= 2 nside``:

        Tsky(nu, L) = [Re sum_m coef[m, nu] exp(-i m L) + Tgnd(nu) sum_below(nu)] / sum_all(nu)

    (``L`` in radians). Nothing here depends on the LST grid or the ground temperature,
    so :func:`~autocal.tsky.compute.compute_tsky` caches it and turns it into a table for any LSTs
    (:meth:`table`) in milliseconds.

    Attributes
    ----------
    freqs
        ``(Nfreq,)`` Hz.
    coef
        ``(M, Nfreq)`` complex harmonics ``m = 0 .. M - 1`` of the above-horizon
        beam-sky overlap (kelvin times beam integral).
    sum_all, sum_below
        ``(Nfreq,)`` the beam integral over the sphere and below the horizon.
    meta
        Description of the sky, beam, site, resolution, epoch and method.
    """

    freqs: np.ndarray
    coef: np.ndarray
    sum_all: np.ndarray
    sum_below: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line: the harmonics' shape and band (never the arrays)."""
        return (
            f"TskyHarmonics({self.coef.shape[0]} harmonics x {self.freqs.size} channels "
            f"{span(self.freqs, 1e6, 'MHz')})"
        )

    def __post_init__(self) -> None:
        nf = self.freqs.shape
        if self.coef.ndim != 2 or self.coef.shape[1:] != nf:
            raise TskyError(f"harmonics of shape {self.coef.shape} do not match {nf[0]} freqs")
        if self.sum_all.shape != nf or self.sum_below.shape != nf:
            raise TskyError("beam integrals must have one value per frequency")

    def table(
        self,
        lsts: np.ndarray | list[float],
        tgnd: float | np.ndarray = T_GROUND,
        meta: dict[str, Any] | None = None,
    ) -> TskyResult:
        """Return Tsky at ``lsts`` (hours) for ground temperature ``tgnd`` (K).

        Parameters
        ----------
        lsts
            LSTs in hours.
        tgnd
            Ground temperature in kelvin (scalar or per frequency).
        meta
            Description stored with the table (default: this object's).

        Returns
        -------
        TskyResult
            The table.
        """
        lsts = check_grid(lsts, "LST")
        tg = tgnd_array(tgnd, self.freqs.size)
        tsky = synthesise(self.coef, lst_radians(lsts))  # (Nlst, Nf): the numerator
        tsky += tg * self.sum_below
        tsky /= self.sum_all
        f_below = self.sum_below / self.sum_all
        return TskyResult(
            tsky=tsky,
            freqs=self.freqs,
            lsts=lsts,
            f_above=1 - f_below,
            f_below=f_below,
            meta=dict(self.meta if meta is None else meta),
        )


def check_grid(values: np.ndarray | list[float] | float, what: str) -> np.ndarray:
    """Return a finite 1-D float array, raising :class:`TskyError` if empty or non-finite."""
    arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if arr.ndim != 1:
        raise TskyError(f"the {what} grid must be one-dimensional")
    if arr.size == 0:
        raise TskyError(f"the {what} grid is empty: give at least one value")
    if not np.all(np.isfinite(arr)):
        raise TskyError(f"the {what} grid has non-finite values")
    return arr


def tgnd_array(tgnd: float | np.ndarray, nfreq: int) -> np.ndarray:
    """Return the ground temperature ``tgnd`` (K) as one value per frequency, ``(nfreq,)``.

    ``tgnd`` is a scalar or has one value per frequency; :class:`TskyError` if it is
    neither, or not finite and >= 0 K.
    """
    arr = np.asarray(tgnd, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(nfreq, float(arr))
    if arr.shape != (nfreq,):
        raise TskyError(
            f"ground temperature must be a scalar or have one value per frequency "
            f"({nfreq}), got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise TskyError("ground temperature must be finite and >= 0 K")
    return arr
