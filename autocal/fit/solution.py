"""The fitted solution: gains and receiver noise per antenna, polarisation and channel.

:class:`Solution` holds the fitted coefficients and their covariance, the fit's statistics
and, when computed, the total uncertainty (:mod:`autocal.fit.total_uncertainty`); its
properties give the time-averaged gain ``G``, offset ``n``, receiver temperature ``Trxr``
and their errors (:func:`trxr_sigma`). Its products are written by the later stages
(:meth:`Solution.to_uvcal`, :meth:`Solution.write`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.reprs import list_summary, median, span
from autocal.fit.model import FitError, FitModel, check_tsky, design
from autocal.fit.sums import NormalSums
from autocal.fit.total_uncertainty import TotalUncertainty


@dataclass(frozen=True, eq=False)
class Solution:
    """Fitted receiver gain and noise per antenna, polarisation and channel.

    Parameters
    ----------
    model
        The fitted model.
    antennas
        ``(Nant,)`` antenna numbers.
    pols
        Polarisation names.
    freqs
        ``(Nfreq,)`` Hz.
    lsts, jds
        ``(Ntime,)`` the fitted integrations (hours; Julian dates).
    coeffs
        ``(Nant, Npol, Nfreq, nparam)``: ``(G, n)`` or ``(g_0..g_p, n_0..n_p)``.
    cov
        ``(Nant, Npol, Nfreq, nparam, nparam)`` parameter covariance.
    chi2, dof
        ``(Nant, Npol, Nfreq)`` chi-square and degrees of freedom (used samples minus
        parameters). With identity weights chi-square is in data units squared.
    count, nflagged
        Used and excluded samples per channel.
    flag_reason
        ``(Nant, Npol, Nfreq)`` int codes (:data:`autocal.fit.solve.FLAG_REASONS`); 0 = solved.
    config
        Resolved configuration: weights, iterations, sky, beam, Tsky conventions, inputs.
    residuals
        Optional ``(Nant, Npol, Ntime, Nfreq)`` normalised residuals ``(R - model) / sigma``
        (identity weights: divided by the fitted residual rms).
    antenna_names
        Names of the antennas.
    total
        The total uncertainty (:class:`autocal.fit.total_uncertainty.TotalUncertainty`): when set,
        ``sigma_G``, ``sigma_n``, ``sigma_Trxr`` and ``sigma_abs_g`` are total errors and
        the ``*_stat`` properties the statistical part alone.
    time_flags
        Optional ``(Nant, Npol, Ntime)`` integrations flagged whole before the fit (RFI in
        time, :mod:`autocal.pipeline.rfi`); the per-time calh5/calfits flag them.

    Notes
    -----
    ``G``, ``n`` and the ``sigma_*`` arrays are computed on first use and kept (read-only:
    copy one to change it); a solution's own arrays are not to be changed after it is made
    (:func:`dataclasses.replace` makes a new one).
    """

    model: FitModel
    antennas: np.ndarray
    pols: tuple[str, ...]
    freqs: np.ndarray
    lsts: np.ndarray
    jds: np.ndarray
    coeffs: np.ndarray
    cov: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    count: np.ndarray
    nflagged: np.ndarray
    flag_reason: np.ndarray
    config: dict[str, Any] = field(default_factory=dict)
    residuals: np.ndarray | None = None
    antenna_names: tuple[str, ...] = ()
    total: TotalUncertainty | None = None
    time_flags: np.ndarray | None = None

    def __post_init__(self) -> None:
        lead = (len(self.antennas), len(self.pols), len(self.freqs))
        m = self.model.nparam
        checks = {
            "coeffs": (self.coeffs, (*lead, m)),
            "cov": (self.cov, (*lead, m, m)),
            "chi2": (self.chi2, lead),
            "dof": (self.dof, lead),
            "count": (self.count, lead),
            "nflagged": (self.nflagged, lead),
            "flag_reason": (self.flag_reason, lead),
        }
        for name, (arr, shape) in checks.items():
            if np.shape(arr) != shape:
                raise FitError(f"Solution.{name} has shape {np.shape(arr)}, expected {shape}")
        if np.shape(self.lsts) != np.shape(self.jds):
            raise FitError("Solution lsts and jds differ in length")
        if self.residuals is not None and self.residuals.shape != (
            lead[0],
            lead[1],
            len(self.lsts),
            lead[2],
        ):
            raise FitError("Solution.residuals has the wrong shape")
        if self.total is not None and self.total.cov.shape != (*lead, 2, 2):
            raise FitError("Solution.total has the wrong shape")
        if self.time_flags is not None and np.shape(self.time_flags) != (
            lead[0],
            lead[1],
            len(self.lsts),
        ):
            raise FitError("Solution.time_flags has the wrong shape")

    @classmethod
    def from_solved(
        cls,
        model: FitModel,
        sums: NormalSums,
        solved: dict[str, np.ndarray],
        *,
        antennas: np.ndarray,
        pols: tuple[str, ...],
        freqs: np.ndarray,
        lsts: np.ndarray,
        jds: np.ndarray,
        antenna_names: tuple[str, ...] = (),
        config: dict[str, Any] | None = None,
        total: TotalUncertainty | None = None,
    ) -> Solution:
        """Build a solution from normal sums and what :func:`~autocal.fit.solve.solve_sums` gave."""
        return cls(
            model=model,
            antennas=np.asarray(antennas),
            pols=tuple(pols),
            freqs=freqs,
            lsts=lsts,
            jds=jds,
            coeffs=solved["coeffs"],
            cov=solved["cov"],
            chi2=solved["chi2"],
            dof=solved["dof"],
            count=sums.count,
            nflagged=sums.nflagged,
            flag_reason=solved["flag_reason"],
            config=config or {},
            antenna_names=antenna_names,
            total=total,
        )

    def __repr__(self) -> str:
        """Return one line: model, axes, ranges and medians (never the arrays)."""
        ok = ~self.flags
        with np.errstate(invalid="ignore", divide="ignore"):
            gain = self.G
            abs_g, trxr = np.sqrt(gain), self.n / gain
        nant = len(self.antennas)
        model = (
            self.model.kind
            if self.model.kind == "constant"
            else (f"legendre order {self.model.order}")
        )
        errors = "statistical" if self.total is None else "total"
        return (
            f"Solution({model}: {nant} antenna{'s' * (nant != 1)} "
            f"{list_summary(self.antennas)}, pols {list_summary(self.pols)}, "
            f"{self.freqs.size} channels {span(self.freqs, 1e6, 'MHz')}, {self.lsts.size} "
            f"times LST {span(self.lsts, 1, 'h')}; {int(self.flags.sum())} flagged; median "
            f"|g| {median(abs_g, ok):.4g}, Trxr {median(trxr, ok):.4g} K "
            f"+- {median(self.sigma_Trxr, ok):.3g} K ({errors}), "
            f"chi2/dof {median(self.reduced_chi2, ok):.3g})"
        )

    # products -------------------------------------------------------------------------
    def to_uvcal(self, **kwargs: Any) -> Any:
        """Return the gains ``|g| = sqrt(G)`` as a pyuvdata ``UVCal``.

        The object the calh5/calfits products hold
        (:func:`autocal.io.calsol_uvcal.solution_to_uvcal`;
        ``kwargs``: ``time_range``, ``per_time``, ``telescope``, ``site``, ``history``).
        """
        # the product writer is a later stage (and loads pyuvdata): imported on use
        from autocal.io.calsol_uvcal import solution_to_uvcal

        return solution_to_uvcal(self, **kwargs)

    def write(
        self,
        out: str | Path,
        products: tuple[str, ...] | list[str] = ("calh5", "hdf5"),
        *,
        overwrite: bool = False,
    ) -> dict[str, str]:
        """Write products of this solution into the folder ``out`` (created).

        The files and writers of ``autocal calibrate``
        (:func:`autocal.pipeline.products.write_solution_products`): ``solution.calh5``,
        ``solution.calfits``, ``solution.h5``, ``solution.png``.

        Parameters
        ----------
        out
            Output folder.
        products
            Any of ``"calh5"``, ``"calfits"``, ``"hdf5"``, ``"png"``.
        overwrite
            Replace existing files (otherwise an existing file is a ``FileExistsError``).

        Returns
        -------
        dict
            Product name -> path.
        """
        # the product writers are a later stage: imported on use
        from autocal.pipeline.products import write_solution_products

        return write_solution_products(self, out, products, overwrite=overwrite)

    # basic quantities ------------------------------------------------------------------
    @property
    def flags(self) -> np.ndarray:
        """``(Nant, Npol, Nfreq)`` ``True`` where the channel could not be solved."""
        return self.flag_reason != 0

    @property
    def time_average(self) -> np.ndarray:
        """``(nbasis,)`` mean of each basis function over the fitted integrations."""
        return self.model.basis(self.lsts).mean(axis=1)

    def _memo(self, key: Any, compute: Callable[[], Any]) -> Any:
        """Return ``compute()``, computed once per solution (its arrays read-only).

        The properties below are evaluated many times by the products and summaries (a
        HERA file's million channels: ~0.1 s each time); the arrays a solution holds are
        not changed after it is made.
        """
        memo = self.__dict__.setdefault("_memoised", {})
        if key not in memo:
            value = compute()
            for arr in value.values() if isinstance(value, dict) else value:
                arr.flags.writeable = False
            memo[key] = value
        return memo[key]

    def _mean_param(self, which: int) -> tuple[np.ndarray, np.ndarray]:
        return self._memo(("mean", which), lambda: self._compute_mean_param(which))

    def _compute_mean_param(self, which: int) -> tuple[np.ndarray, np.ndarray]:
        nb = self.model.nbasis
        v = np.zeros(self.model.nparam)
        v[which * nb : (which + 1) * nb] = self.time_average
        value = self.coeffs @ v
        var = np.einsum("i,...ij,j->...", v, self.cov, v)
        return value, var

    @property
    def G(self) -> np.ndarray:
        """Gain ``G = |g|^2`` averaged over the fitted integrations."""
        return self._mean_param(0)[0]

    @property
    def n(self) -> np.ndarray:
        """Noise offset ``n = G Trxr`` averaged over the fitted integrations."""
        return self._mean_param(1)[0]

    @property
    def sigma_G(self) -> np.ndarray:
        """1-sigma uncertainty of :attr:`G`: the total when known, else statistical."""
        return self._sigmas()["sigma_G"]

    @property
    def sigma_n(self) -> np.ndarray:
        """1-sigma uncertainty of :attr:`n`: the total when known, else statistical."""
        return self._sigmas()["sigma_n"]

    @property
    def sigma_Trxr(self) -> np.ndarray:
        """1-sigma uncertainty of :attr:`Trxr`: the total when known, else statistical.

        Linear propagation, ``Var(Trxr) = Trxr^2 [C_GG / G^2 + C_nn / n^2 - 2 C_Gn / (G
        n)]``, the paper's ``sum_ij (-1)^(i+j) C_ij / (x_i x_j)`` written out (the cross
        term enters with a minus sign because ``d(n/G)/dG = -n/G^2``).
        """
        return self._sigmas()["sigma_Trxr"]

    @property
    def sigma_abs_g(self) -> np.ndarray:
        """1-sigma uncertainty of ``|g|``, ``sigma_G / (2 |g|)``: total when known."""
        return self._sigmas()["sigma_abs_g"]

    @property
    def sigma_G_stat(self) -> np.ndarray:
        """Statistical 1-sigma of :attr:`G` (the fit's covariance)."""
        return self._sigmas(stat=True)["sigma_G"]

    @property
    def sigma_n_stat(self) -> np.ndarray:
        """Statistical 1-sigma of :attr:`n`."""
        return self._sigmas(stat=True)["sigma_n"]

    @property
    def sigma_Trxr_stat(self) -> np.ndarray:
        """Statistical 1-sigma of :attr:`Trxr`."""
        return self._sigmas(stat=True)["sigma_Trxr"]

    @property
    def sigma_abs_g_stat(self) -> np.ndarray:
        """Statistical 1-sigma of ``|g|``."""
        return self._sigmas(stat=True)["sigma_abs_g"]

    @property
    def cov_mean(self) -> np.ndarray:
        """Statistical covariance ``(Nant, Npol, Nfreq, 2, 2)`` of the time-averaged ``(G, n)``."""
        gg, nn = self._mean_param(0)[1], self._mean_param(1)[1]
        gn = self._mean_cov_gn()
        return np.stack([np.stack([gg, gn], -1), np.stack([gn, nn], -1)], -2)

    @property
    def cov_mean_total(self) -> np.ndarray:
        """Total covariance of the time-averaged ``(G, n)`` (statistical without a total)."""
        return self.cov_mean if self.total is None else self.total.cov

    def _sigmas(self, stat: bool = False) -> dict[str, np.ndarray]:
        stat = stat or self.total is None
        return self._memo(("sigmas", stat), lambda: self._compute_sigmas(stat))

    def _compute_sigmas(self, stat: bool) -> dict[str, np.ndarray]:
        cov = self.cov_mean if stat or self.total is None else self.total.cov
        var_g, var_n, cgn = cov[..., 0, 0], cov[..., 1, 1], cov[..., 0, 1]
        g, n = self.G, self.n
        with np.errstate(invalid="ignore", divide="ignore"):
            sg = np.sqrt(var_g)
            return {
                "sigma_G": sg,
                "sigma_n": np.sqrt(var_n),
                "sigma_Trxr": trxr_sigma(g, n, var_g, var_n, cgn),
                "sigma_abs_g": sg / (2 * np.sqrt(g)),
            }

    def _mean_cov_gn(self) -> np.ndarray:
        nb = self.model.nbasis
        vg = np.zeros(self.model.nparam)
        vn = np.zeros(self.model.nparam)
        vg[:nb] = self.time_average
        vn[nb:] = self.time_average
        return np.einsum("i,...ij,j->...", vg, self.cov, vn)

    @property
    def Trxr(self) -> np.ndarray:
        """Receiver temperature ``n / G`` (time-averaged ``n`` over time-averaged ``G``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.n / self.G

    @property
    def abs_g(self) -> np.ndarray:
        """Gain amplitude ``|g| = sqrt(G)`` (NaN where flagged)."""
        with np.errstate(invalid="ignore"):
            return np.sqrt(self.G)

    @property
    def reduced_chi2(self) -> np.ndarray:
        """``chi^2 / dof`` (NaN where ``dof <= 0``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.dof > 0, self.chi2 / self.dof, np.nan)

    # the time model --------------------------------------------------------------------
    def evaluate(self, lsts: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Evaluate ``G(t)``, ``n(t)``, ``Trxr(t)`` and their statistical 1-sigma errors.

        The total uncertainty (:attr:`total`) is that of the time averages; these errors
        are the time model's covariance propagated to each LST.

        Parameters
        ----------
        lsts
            LSTs in hours (default: the fitted integrations).

        Returns
        -------
        dict
            ``G``, ``n``, ``Trxr``, ``sigma_G``, ``sigma_n``, ``sigma_Trxr``, each
            ``(Nant, Npol, Ntime, Nfreq)``.
        """
        lsts = self.lsts if lsts is None else np.atleast_1d(np.asarray(lsts, np.float64))
        nb = self.model.nbasis
        basis = self.model.basis(lsts)  # (K, T)
        g = np.einsum("kt,apfk->aptf", basis, self.coeffs[..., :nb])
        n = np.einsum("kt,apfk->aptf", basis, self.coeffs[..., nb:])
        cgg = self.cov[..., :nb, :nb]
        cnn = self.cov[..., nb:, nb:]
        cgn = self.cov[..., :nb, nb:]
        var_g = np.einsum("kt,apfkl,lt->aptf", basis, cgg, basis)
        var_n = np.einsum("kt,apfkl,lt->aptf", basis, cnn, basis)
        cov_gn = np.einsum("kt,apfkl,lt->aptf", basis, cgn, basis)
        with np.errstate(divide="ignore", invalid="ignore"):
            trxr = n / g
        return {
            "G": g,
            "n": n,
            "Trxr": trxr,
            "sigma_G": np.sqrt(var_g),
            "sigma_n": np.sqrt(var_n),
            "sigma_Trxr": trxr_sigma(g, n, var_g, var_n, cov_gn),
        }

    def predict(self, tsky: np.ndarray, lsts: np.ndarray | None = None) -> np.ndarray:
        """Model auto-correlations ``G(t) Tsky + n(t)``, ``(Nant, Npol, Ntime, Nfreq)``."""
        lsts = self.lsts if lsts is None else np.asarray(lsts, np.float64)
        a = design(self.model, check_tsky(tsky, len(self.pols), lsts.size, self.freqs.size), lsts)
        return np.einsum("pftm,apfm->aptf", a, self.coeffs)

    def describe(self) -> dict[str, Any]:
        """Short JSON-serialisable summary (medians over unflagged channels)."""
        ok = ~self.flags

        def med(x: np.ndarray) -> float | None:
            with np.errstate(invalid="ignore", divide="ignore"):
                vals = x[ok & np.isfinite(x)]
            return float(np.median(vals)) if vals.size else None

        gain = self.G  # every property below is computed once (a HERA file: 1 M channels)
        total, stat = self._sigmas(), self._sigmas(stat=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            abs_g, trxr = np.sqrt(gain), self.n / gain
            frac, frac_stat = total["sigma_G"] / gain, stat["sigma_G"] / gain
        return {
            "model": self.model.describe(),
            "antennas": self.antennas.tolist(),
            "pols": list(self.pols),
            "nfreq": int(self.freqs.size),
            "ntime": int(self.lsts.size),
            "flagged_channels": int(self.flags.sum()),
            "median_G": med(gain),
            "median_abs_g": med(abs_g),
            "median_Trxr_K": med(trxr),
            "median_sigma_Trxr_K": med(total["sigma_Trxr"]),
            "median_sigma_Trxr_stat_K": med(stat["sigma_Trxr"]),
            "median_sigma_G_frac": med(frac),
            "median_sigma_G_stat_frac": med(frac_stat),
            "errors": "statistical" if self.total is None else "total",
            "weak_separation": None if self.total is None else int(np.sum(self.total.separation())),
            "median_reduced_chi2": med(self.reduced_chi2),
        }


def trxr_sigma(
    g: np.ndarray, n: np.ndarray, var_g: np.ndarray, var_n: np.ndarray, cov_gn: np.ndarray
) -> np.ndarray:
    """Propagate ``(G, n)`` errors to ``Trxr = n / G`` (first order).

    ``Var(Trxr) = Trxr^2 [Var(G)/G^2 + Var(n)/n^2 - 2 Cov(G, n)/(G n)]``.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        trxr = n / g
        var = trxr**2 * (var_g / g**2 + var_n / n**2 - 2 * cov_gn / (g * n))
    return np.sqrt(np.where(var >= 0, var, np.nan))
